# shellcheck shell=bash
# Sourced by docker/check_compose.sh and docker/check_arm64.sh (root, Debian bookworm): Debian's
# packages they need and the podman settings this VM needs, in one place.
#
# Podman setup this was proven with (Debian 12, podman 4.3.1, podman-compose 1.0.3, rootful):
#   storage overlay (the default), network backend netavark + aardvark-dns (service names resolve),
#   OCI runtime runc: crun 1.8 refuses this VM's hybrid cgroup v1/v2 layout ("cgroups in hybrid mode
#   not supported"); default_ulimits nofile=1024:20000 / nproc=1024:1024 because the default
#   RLIMIT_NOFILE request fails here ("setrlimit RLIMIT_NOFILE: Operation not permitted");
#   log_driver k8s-file (no journald). All four go into the containers.conf drop-in below.

NICE=(nice -n 19)
CA_BUNDLE="${CA_BUNDLE:-/etc/ssl/certs/ca-certificates.crt}"  # handed to pip as a build secret if present
log() { printf '\n=== %s\n' "$*"; }

# install_packages PKG...: apt-get install those of PKG... not installed yet.
install_packages() {
    local need=() pkg
    for pkg in "$@"; do
        dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "ok installed" || need+=("$pkg")
    done
    if ((${#need[@]})); then
        "${NICE[@]}" apt-get update -qq
        DEBIAN_FRONTEND=noninteractive "${NICE[@]}" apt-get install -y -qq "${need[@]}"
    fi
}

# write_containers_conf: the drop-in with the settings above.
write_containers_conf() {
    mkdir -p /etc/containers/containers.conf.d
    cat > /etc/containers/containers.conf.d/50-triscan.conf <<'CONF'
# written by triscan docker/podman-host.sh
[containers]
default_ulimits = ["nofile=1024:20000", "nproc=1024:1024"]
log_driver = "k8s-file"
[engine]
runtime = "runc"
CONF
    podman info -f 'runtime={{.Host.OCIRuntime.Name}} storage={{.Store.GraphDriverName}} network={{.Host.NetworkBackend}} cgroups=v{{.Host.CgroupsVersion}}'
}

# build_args: the podman build flags both checks pass (base image, index, CA bundle as a build secret).
# Reads BASE_IMAGE, PIP_INDEX_URL and CA_BUNDLE; fills the array BUILD_ARGS.
build_args() {
    BUILD_ARGS=(--build-arg "BASE_IMAGE=$BASE_IMAGE")
    [[ -n "${PIP_INDEX_URL:-}" ]] && BUILD_ARGS+=(--build-arg "PIP_INDEX_URL=$PIP_INDEX_URL")
    [[ -s "$CA_BUNDLE" ]] && BUILD_ARGS+=(--secret "id=ca,src=$CA_BUNDLE")
    return 0
}

# check_robot_image IMAGE: the robot image is slim (no torch, PyBullet, rerun, Ultralytics), holds the
# `ros2` extra (rosbags) for the ROS 2 bridge, the bridge starts in it, and the installed `triscan`
# command finds its default model in the installed package.
check_robot_image() {
    local image=$1 pkgs
    pkgs=$(podman run --rm --entrypoint python "$image" -c \
        'import importlib.metadata as m; print(" ".join(sorted(d.metadata["Name"].lower() for d in m.distributions())))')
    echo "robot image packages: $pkgs"
    if grep -qwE 'torch|pybullet|rerun-sdk|ultralytics' <<<"$pkgs"; then echo "FAIL: $image is not slim"; return 1; fi
    if ! grep -qw rosbags <<<"$pkgs"; then echo "FAIL: $image lacks rosbags (the ros2 extra)"; return 1; fi
    podman run --rm --entrypoint python "$image" -m services.ros2_bridge --help >/dev/null \
        || { echo "FAIL: services.ros2_bridge does not start in $image"; return 1; }
    podman run --rm --entrypoint triscan "$image" --help >/dev/null \
        || { echo "FAIL: the triscan command does not start in $image"; return 1; }
    podman run --rm --entrypoint python "$image" -c \
        'from common.model_spec import default_model_path as d; assert d().is_file() and d(True).is_file(), d()' \
        || { echo "FAIL: $image lacks the default model"; return 1; }
}
