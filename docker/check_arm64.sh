#!/usr/bin/env bash
# Does the robot image work on a 64-bit ARM robot (Raspberry Pi 5 and the like)? Checked on this x86-64
# machine under emulation, with Debian's podman and qemu-user-static (root; not in CI: it takes long).
#   1. an arm64 Debian bookworm base image: docker/base.sh with ARCH=arm64 (mmdebstrap --architectures=arm64,
#      its maintainer scripts run under qemu through binfmt_misc);
#   2. the robot image for linux/arm64 from docker/Dockerfile (every RUN, pip included, is emulated);
#   3. the detector in it, `python -m services.detector --from-scans`, emulated, on the host's network,
#      given a Raspberry Pi 5's /proc/cpuinfo (see PI5_CPUINFO below);
#   4. from the host: a bag of simulated scans (triscan sim-bag) replayed at recorded pace into it by
#      bench/replay_answered.py, which waits for the detector and measures what comes back.
# PASS when detections of the replayed scans come back to the host from the arm64 container; prints the
# build times, the detector's start time, the share of scans answered, latency and the detector's own
# per-frame inference time (emulated: qemu runs arm64 code several times slower than the real thing, so
# these are not Pi figures; at 10 Hz the emulated detector may answer only some scans, dropping stale
# ones by design, which the check reports but does not fail on).
#   sudo docker/check_arm64.sh     env: SCANS=100 SPEED=1 PORT=7460 PY=.venv/bin/python
#                                       BASE_IMAGE=triscan-base:bookworm-arm64 CA_BUNDLE=... PIP_INDEX_URL=
#                                       KEEP=0 (1: leave the detector container running)
# PY must be a host venv with the dev extras (`pip install -e '.[sim,dev]'`: PyBullet for the scans,
# rosbags for the bag, zenoh).
set -euo pipefail
cd "$(dirname "$0")/.."
# shellcheck source=docker/podman-host.sh
source docker/podman-host.sh
SCANS="${SCANS:-100}"
SPEED="${SPEED:-1}"
PORT="${PORT:-7460}"
PY="${PY:-.venv/bin/python}"
BASE_IMAGE="${BASE_IMAGE:-triscan-base:bookworm-arm64}"
IMAGE=triscan-robot:arm64
CONTAINER=triscan-arm64-detector
START=$(date +%s)
WORK="$(mktemp -d /tmp/triscan-arm64.XXXXXX)"

[[ $EUID -eq 0 ]] || { echo "run as root (rootful podman, binfmt_misc)"; exit 2; }
# shellcheck disable=SC2317  # run by the EXIT trap
cleanup() {
    [[ "${KEEP:-0}" == 1 ]] || podman rm -f "$CONTAINER" >/dev/null 2>&1 || true
    rm -rf "$WORK"
}
trap cleanup EXIT

log "packages"
install_packages podman mmdebstrap runc qemu-user-static binfmt-support arch-test
echo "podman $(podman version -f '{{.Client.Version}}'), $(dpkg-query -W -f='qemu-user-static ${Version}' qemu-user-static)"
write_containers_conf

log "arm64 emulation (binfmt_misc)"
if [[ ! -e /proc/sys/fs/binfmt_misc/register ]]; then
    mount -t binfmt_misc binfmt_misc /proc/sys/fs/binfmt_misc
fi
update-binfmts --enable qemu-aarch64 2>/dev/null || true
# F (fix binary): the kernel keeps the interpreter open, so it works inside containers and chroots too
grep -q '^flags: .*F' /proc/sys/fs/binfmt_misc/qemu-aarch64 \
    || { echo "FAIL: qemu-aarch64 is not registered with the F flag"; exit 1; }
arch-test arm64 || { echo "FAIL: this kernel cannot run arm64 binaries through qemu"; exit 1; }

log "host environment"
"$PY" -c 'import zenoh, rosbags, pybullet' || { echo "FAIL: $PY lacks zenoh, rosbags or pybullet"; exit 2; }
echo "$PY"

log "arm64 base image $BASE_IMAGE"
t0=$(date +%s)
ARCH=arm64 docker/base.sh "$BASE_IMAGE"
echo "base image ready in $(( $(date +%s) - t0 )) s"

log "robot image $IMAGE (linux/arm64, emulated build)"
build_args
t0=$(date +%s)
"${NICE[@]}" podman build -q --platform linux/arm64 -f docker/Dockerfile --target robot "${BUILD_ARGS[@]}" \
    -t "$IMAGE" . >/dev/null
build_s=$(( $(date +%s) - t0 ))
echo "$IMAGE built in $build_s s"
arch=$(podman image inspect -f '{{.Architecture}}' "$IMAGE")
machine=$(podman run --rm --entrypoint python "$IMAGE" -c 'import platform; print(platform.machine())')
echo "image architecture: $arch; python in it runs on: $machine"
[[ $arch == arm64 && $machine == aarch64 ]] || { echo "FAIL: $IMAGE is not an arm64 image"; exit 1; }
check_robot_image "$IMAGE"

# Under qemu-user a container reads the host's /proc/cpuinfo (x86: no "CPU part" lines), and ONNX
# Runtime's cpuinfo library, which identifies ARM cores from that file, crashes while the module loads
# (onnxruntime 1.32, qemu 7.2: SIGSEGV in `import onnxruntime`). A real Pi 5 has the file below (two
# of its four Cortex-A76 cores, as this VM has two CPUs); the containers get it, and nothing else
# changes.
PI5_CPUINFO="$WORK/cpuinfo"
for cpu in 0 1; do
    printf 'processor\t: %d\nBogoMIPS\t: 108.00\nFeatures\t: fp asimd evtstrm aes pmull sha1 sha2 crc32 atomics fphp asimdhp cpuid asimdrdm lrcpc dcpop asimddp\nCPU implementer\t: 0x41\nCPU architecture: 8\nCPU variant\t: 0x4\nCPU part\t: 0xd0b\nCPU revision\t: 1\n\n' "$cpu"
done >"$PI5_CPUINFO"
ARM_RUN=(podman run --rm -v "$PI5_CPUINFO:/proc/cpuinfo:ro")

log "ONNX Runtime in the arm64 image (emulated): load the shipped model, run one frame"
"${ARM_RUN[@]}" --entrypoint python "$IMAGE" -c '
import time
import numpy as np
from common.inference import OnnxDetector
from common.model_spec import default_model_path
t0 = time.perf_counter()
detector = OnnxDetector(default_model_path(), intra_op_threads=1)
t1 = time.perf_counter()
detector.detect(np.zeros((64, 384, 3), np.uint8))
print(f"model loaded in {t1 - t0:.1f} s, one frame in {time.perf_counter() - t1:.2f} s (emulated)")
' || { echo "FAIL: ONNX Runtime does not run the model in $IMAGE"; exit 1; }

log "the detector in the arm64 container (--from-scans, emulated)"
podman rm -f "$CONTAINER" >/dev/null 2>&1 || true
t_start=$(date +%s)
# --init: the detector is not PID 1, so a crash ends the container instead of hanging it (PID 1 ignores
# the signal qemu re-raises to die)
podman run -d --init --name "$CONTAINER" --network host -v "$PI5_CPUINFO:/proc/cpuinfo:ro" "$IMAGE" \
    python -m services.detector --from-scans --listen "tcp/127.0.0.1:$PORT" --no-multicast >/dev/null
for _ in $(seq 300); do
    (exec 3<>"/dev/tcp/127.0.0.1/$PORT") 2>/dev/null && break
    [[ $(podman inspect -f '{{.State.Status}}' "$CONTAINER" 2>/dev/null) == running ]] || break
    sleep 1
done
echo "its Zenoh port $PORT open after $(( $(date +%s) - t_start )) s"

log "a bag of $SCANS simulated scans, replayed from the host into it"
"${NICE[@]}" "$PY" -m services.cli sim-bag --scans "$SCANS" --out "$WORK/bag"
status=0
# --wait: the emulated detector loads ONNX Runtime and the model before it subscribes and answers
"$PY" -m bench.replay_answered --bag "$WORK/bag" --connect "tcp/127.0.0.1:$PORT" --speed "$SPEED" \
    --wait 900 --out "$WORK/replay.json" >"$WORK/replay.txt" 2>&1 || true
ready_s=$(( $(date +%s) - t_start ))
if ! "$PY" - "$WORK/replay.json" <<'PY'
import json, sys
r = json.load(open(sys.argv[1]))
print(f"answered {r['scans_answered']}/{r['scans_answerable']} scans ({100 * r['answered_share']:.1f} %), "
      f"{r['objects_per_frame']} objects per frame")
print(f"scan put -> detections on the host: {r['latency_ms']}")
print(f"detector per frame, emulated arm64 (ms, p50): {r['detector_stage_ms_p50']}")
print(f"detector counters: {r['detector_counters']}")
sys.exit(0 if r["scans_answered"] > 0 else 1)
PY
then
    status=1
    tail -20 "$WORK/replay.txt"
    podman logs --tail 20 "$CONTAINER" 2>&1 | sed 's/^/detector log: /'
fi
state=$(podman inspect -f '{{.State.Status}}' "$CONTAINER" 2>/dev/null || echo missing)
echo "detector container after the replay: $state"
[[ $state == running ]] || status=1

log "summary"
echo "robot image (arm64) built in $build_s s; detector started and answered within $ready_s s"
echo "total time $(( $(date +%s) - START )) s; result: $( ((status)) && echo FAIL || echo PASS)"
exit $status
