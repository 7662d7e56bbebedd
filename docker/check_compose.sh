#!/usr/bin/env bash
# End-to-end check of compose.yaml with podman on Debian bookworm (root): install podman and friends,
# build the local base image and the three triscan images, `podman-compose up` the full loop, subscribe
# from the host to triscan/*/detections through the detector's published port for $DURATION seconds,
# act as a ROS 2 node on rmw_zenoh inside the ros2_bridge container (docker/check_ros2_bridge.py:
# LaserScans in, Detection3DArrays back), `podman-compose down`, print a summary. Exits non-zero unless
# every simulated robot delivered detections to the host, the bridge answered the ROS 2 node, the robot
# image holds rosbags but no torch/pybullet/rerun, every container is still running, and the web viewer
# answers.
#   docker/check_compose.sh        env: DURATION=30 ROBOTS=2 BASE_IMAGE=triscan-base:bookworm
#                                       CA_BUNDLE=/etc/ssl/certs/ca-certificates.crt PIP_INDEX_URL= KEEP_UP=0
#
# Podman setup this was proven with (Debian 12, podman 4.3.1, podman-compose 1.0.3, rootful):
#   storage overlay (the default), network backend netavark + aardvark-dns (service names resolve),
#   OCI runtime runc: crun 1.8 refuses this VM's hybrid cgroup v1/v2 layout ("cgroups in hybrid mode
#   not supported"); default_ulimits nofile=1024:20000 / nproc=1024:1024 because the default
#   RLIMIT_NOFILE request fails here ("setrlimit RLIMIT_NOFILE: Operation not permitted");
#   log_driver k8s-file (no journald). All four go into a containers.conf drop-in below.
set -euo pipefail
cd "$(dirname "$0")/.."
DURATION="${DURATION:-30}"
ROBOTS="${ROBOTS:-2}"
BASE_IMAGE="${BASE_IMAGE:-triscan-base:bookworm}"
CA_BUNDLE="${CA_BUNDLE:-/etc/ssl/certs/ca-certificates.crt}"
PROJECT=triscan
START=$(date +%s)
NICE=(nice -n 19)
log() { printf '\n=== %s\n' "$*"; }

[[ $EUID -eq 0 ]] || { echo "run as root (rootful podman)"; exit 2; }

log "packages"
need=()
for pkg in podman podman-compose mmdebstrap runc; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "ok installed" || need+=("$pkg")
done
if ((${#need[@]})); then
    "${NICE[@]}" apt-get update -qq
    DEBIAN_FRONTEND=noninteractive "${NICE[@]}" apt-get install -y -qq "${need[@]}"
fi
echo "podman $(podman version -f '{{.Client.Version}}'), $(podman-compose version 2>/dev/null | grep -m1 podman-compose || echo podman-compose)"

log "containers.conf drop-in"
mkdir -p /etc/containers/containers.conf.d
cat > /etc/containers/containers.conf.d/50-triscan.conf <<'CONF'
# written by triscan docker/check_compose.sh
[containers]
default_ulimits = ["nofile=1024:20000", "nproc=1024:1024"]
log_driver = "k8s-file"
[engine]
runtime = "runc"
CONF
podman info -f 'runtime={{.Host.OCIRuntime.Name}} storage={{.Store.GraphDriverName}} network={{.Host.NetworkBackend}} cgroups=v{{.Host.CgroupsVersion}}'

log "base image $BASE_IMAGE"
if [[ "$BASE_IMAGE" == triscan-base:* ]]; then docker/base.sh "$BASE_IMAGE"; fi

log "images"
build=(--build-arg "BASE_IMAGE=$BASE_IMAGE")
[[ -n "${PIP_INDEX_URL:-}" ]] && build+=(--build-arg "PIP_INDEX_URL=$PIP_INDEX_URL")
[[ -s "$CA_BUNDLE" ]] && build+=(--secret "id=ca,src=$CA_BUNDLE")
for target in robot simulator visualizer; do
    t0=$(date +%s)
    "${NICE[@]}" podman build -q -f docker/Dockerfile --target "$target" "${build[@]}" -t "triscan-$target:latest" . >/dev/null
    echo "triscan-$target built in $(( $(date +%s) - t0 )) s"
done
pkgs=$(podman run --rm --entrypoint python triscan-robot:latest -c \
    'import importlib.metadata as m; print(" ".join(sorted(d.metadata["Name"].lower() for d in m.distributions())))')
echo "robot image packages: $pkgs"
if grep -qwE 'torch|pybullet|rerun-sdk|ultralytics' <<<"$pkgs"; then echo "FAIL: robot image is not slim"; exit 1; fi
# the ros2_bridge service runs from the robot image: it needs the `ros2` extra (rosbags)
if ! grep -qw rosbags <<<"$pkgs"; then echo "FAIL: robot image lacks rosbags (ros2 extra)"; exit 1; fi
podman run --rm --entrypoint python triscan-robot:latest -m services.ros2_bridge --help >/dev/null \
    || { echo "FAIL: services.ros2_bridge does not start in the robot image"; exit 1; }

log "host subscriber environment"
PY=/tmp/venvtest/t/bin/python
if ! { [[ -x $PY ]] && $PY -c 'import zenoh, msgpack, numpy, pydantic' 2>/dev/null; }; then
    PY=/tmp/triscan-check-venv/bin/python
    if ! { [[ -x $PY ]] && $PY -c 'import zenoh, msgpack, numpy, pydantic' 2>/dev/null; }; then
        python3 -m venv /tmp/triscan-check-venv
        "${NICE[@]}" $PY -m pip install -q "eclipse-zenoh>=1.0,<2" "msgpack>=1.0" "numpy>=1.26" "pydantic>=2.6,<3"
    fi
fi
echo "$PY"

compose=(podman-compose -p "$PROJECT" -f compose.yaml)
down() { [[ "${KEEP_UP:-0}" == 1 ]] || "${compose[@]}" down >/dev/null 2>&1 || true; }
trap down EXIT
"${compose[@]}" down >/dev/null 2>&1 || true

log "podman-compose up (SIM_ROBOTS=$ROBOTS)"
t_up=$(date +%s)
SIM_ROBOTS="$ROBOTS" "${compose[@]}" up -d >/dev/null
podman ps --filter "label=io.podman.compose.project=$PROJECT" --format '{{.Names}}  {{.Image}}  {{.Status}}  {{.Ports}}'
for _ in $(seq 60); do (exec 3<>/dev/tcp/127.0.0.1/7447) 2>/dev/null && break; sleep 2; done
echo "detector port 7447 open after $(( $(date +%s) - t_up )) s"

log "subscribing on the host for $DURATION s"
status=0
$PY docker/check_subscriber.py --connect tcp/127.0.0.1:7447 --duration "$DURATION" --robots "$ROBOTS" \
    | tee /tmp/triscan-check-subscriber.txt || status=1

log "ROS 2 node on rmw_zenoh -> ros2_bridge -> encoder -> detector -> Detection3DArray"
podman exec -i "${PROJECT}_ros2_bridge_1" python - --connect tcp/127.0.0.1:7447 < docker/check_ros2_bridge.py \
    | tee /tmp/triscan-check-ros2.txt || status=1

log "containers after the run"
for svc in simulator encoder detector ros2_bridge visualizer; do
    name="${PROJECT}_${svc}_1"
    state=$(podman inspect -f '{{.State.Status}} restarts={{.RestartCount}}' "$name" 2>/dev/null || echo missing)
    echo "$name: $state"
    [[ $state == "running restarts=0" ]] || status=1
done
web=$(curl -s -o /dev/null -w '%{http_code}' http://127.0.0.1:9090/ || true)
echo "web viewer http://127.0.0.1:9090/ -> HTTP $web"
[[ $web == 200 ]] || status=1
if ((status)); then
    for svc in simulator encoder detector ros2_bridge visualizer; do
        echo "--- logs ${PROJECT}_${svc}_1"; podman logs --tail 20 "${PROJECT}_${svc}_1" 2>&1 || true
    done
else
    podman logs --tail 3 "${PROJECT}_detector_1" 2>&1 | sed 's/^/detector log: /'
fi

log "fault: kill -9 the encoder's process (a crash, not a manual stop); compose must restart it"
if ((status == 0)); then
    victim="${PROJECT}_encoder_1"
    kill -9 "$(podman inspect -f '{{.State.Pid}}' "$victim")"
    t_kill=$(date +%s)
    for _ in $(seq 60); do
        state=$(podman inspect -f '{{.State.Status}} {{.RestartCount}}' "$victim" 2>/dev/null || echo "missing 0")
        [[ $state == running* && ${state#* } -ge 1 ]] && break
        sleep 0.5
    done
    echo "$victim after the kill: $state (after $(( $(date +%s) - t_kill )) s)"
    [[ $state == running* && ${state#* } -ge 1 ]] || status=1
    $PY docker/check_subscriber.py --connect tcp/127.0.0.1:7447 --duration 10 --robots "$ROBOTS" \
        | tee /tmp/triscan-check-after-fault.txt || status=1
fi

log "summary"
podman images --format '{{.Repository}}:{{.Tag}} {{.Size}}' | grep -E 'triscan-(base|robot|simulator|visualizer)'
grep -E '^(TOTAL|  robot|OK|FAIL)' /tmp/triscan-check-subscriber.txt || true
grep -E '^(published|OK|FAIL)' /tmp/triscan-check-ros2.txt || true
echo "total time $(( $(date +%s) - START )) s; result: $( ((status)) && echo FAIL || echo PASS)"
exit $status
