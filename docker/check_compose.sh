#!/usr/bin/env bash
# End-to-end check of compose.yaml with podman on Debian bookworm (root): install podman and friends,
# build the local base image and the three triscan images, `podman-compose up` the full loop, subscribe
# from the host to triscan/*/detections through the detector's published port for $DURATION seconds,
# act as a ROS 2 node on rmw_zenoh inside the ros2_bridge container (docker/check_ros2_bridge.py:
# LaserScans in, Detection3DArrays back), `podman-compose down`, print a summary. Exits non-zero unless
# every simulated robot delivered detections to the host, the bridge answered the ROS 2 node, the robot
# image holds rosbags but no torch/pybullet/rerun, `triscan status` in the detector's container lists the
# services, every container is still running, and the web viewer answers.
#   docker/check_compose.sh        env: DURATION=30 ROBOTS=2 BASE_IMAGE=triscan-base:bookworm
#                                       CA_BUNDLE=/etc/ssl/certs/ca-certificates.crt PIP_INDEX_URL= KEEP_UP=0
# The podman setup it needs (and was proven with) is in docker/podman-host.sh.
set -euo pipefail
cd "$(dirname "$0")/.."
# shellcheck source=docker/podman-host.sh
source docker/podman-host.sh
DURATION="${DURATION:-30}"
ROBOTS="${ROBOTS:-2}"
BASE_IMAGE="${BASE_IMAGE:-triscan-base:bookworm}"
PROJECT=triscan
START=$(date +%s)

[[ $EUID -eq 0 ]] || { echo "run as root (rootful podman)"; exit 2; }

log "packages"
install_packages podman podman-compose mmdebstrap runc
echo "podman $(podman version -f '{{.Client.Version}}'), $(podman-compose version 2>/dev/null | grep -m1 podman-compose || echo podman-compose)"

log "containers.conf drop-in"
write_containers_conf

log "base image $BASE_IMAGE"
if [[ "$BASE_IMAGE" == triscan-base:* ]]; then docker/base.sh "$BASE_IMAGE"; fi

log "images"
build_args
for target in robot simulator visualizer; do
    t0=$(date +%s)
    "${NICE[@]}" podman build -q -f docker/Dockerfile --target "$target" "${BUILD_ARGS[@]}" -t "triscan-$target:latest" . >/dev/null
    echo "triscan-$target built in $(( $(date +%s) - t0 )) s"
done
check_robot_image triscan-robot:latest

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
# shellcheck disable=SC2317  # run by the EXIT trap
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

log "triscan status inside the detector's container (the robot image's installed command)"
podman exec "${PROJECT}_detector_1" triscan status --connect tcp/127.0.0.1:7447 --no-multicast \
    | tee /tmp/triscan-check-status.txt || status=1

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
