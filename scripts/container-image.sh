#!/usr/bin/env bash
# Build and run the rig image with Debian's podman, where no image registry is reachable.
#
#   scripts/container-image.sh build [TAG]        -> builds the Dockerfile, prints TAG
#   scripts/container-image.sh run TAG [ARG...]   -> podman run --rm --network none TAG ARG...
#   scripts/container-image.sh podman [ARG...]    -> podman with the settings below
#
# What it takes (measured on the Debian 12 development VMs):
# - podman + runc from Debian (scripts/ensure-debian-packages.sh installs them): crun
#   refuses these VMs' hybrid cgroups and their RLIMIT_NOFILE, so runc with the cgroupfs
#   manager, and a containers.conf with `default_ulimits = []` (no ulimit forced on the
#   containers); events to a file (no journald);
# - a base image from `debootstrap --variant=minbase` of bookworm (python3, venv, pip,
#   CA certificates) against the mirror apt is configured with, imported with
#   `podman import` and given to the Dockerfile as `--build-arg BASE=` (its default, the
#   slim Python image, needs a registry).  The base is kept (tag by mirror + package
#   list + month: refreshed monthly) and built once per machine, under a lock;
# - the build reaches the package registry with the machine's CA bundle and pip.conf
#   mounted read-only, in the host's network namespace (no container network set-up);
# - all images live in a storage of their own ($RIG_IMAGE_CACHE/storage, default
#   ~/.cache/rig-image): pruning after a build never touches other images.
#
# Exit status 3 (and the reason on stderr) where podman cannot run: not root, no
# apt/podman, or podman failing its own `info`.  The test suite then skips, saying why.
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
root="$(dirname "$here")"
cache="${RIG_IMAGE_CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/rig-image}"
runroot="${XDG_RUNTIME_DIR:-/run}/rig-image"
suite=bookworm
include=python3,python3-venv,python3-pip,ca-certificates

cannot() { echo "container-image: cannot run podman here: $*" >&2; exit 3; }

[ "$(id -u)" -eq 0 ] || cannot "needs root (rootful podman, debootstrap)"
command -v apt-get >/dev/null 2>&1 || cannot "not a Debian system (no apt-get)"
bash "$here/ensure-debian-packages.sh" podman runc debootstrap
for tool in podman /usr/sbin/runc /usr/sbin/debootstrap; do
    command -v "$tool" >/dev/null 2>&1 || cannot "$tool is not installed"
done

mkdir -p "$cache" "$runroot"
conf="$cache/containers.conf"
cat > "$conf" <<'EOF'
[containers]
default_ulimits = []

[engine]
cgroup_manager = "cgroupfs"
runtime = "runc"
events_logger = "file"
EOF
export CONTAINERS_CONF="$conf"
pod() {
    podman --root "$cache/storage" --runroot "$runroot" --runtime /usr/sbin/runc \
        --cgroup-manager cgroupfs "$@"
}
pod info >/dev/null 2>"$cache/info.err" || cannot "podman info failed: $(tail -n 3 "$cache/info.err")"

# The Debian mirror apt uses (deb822 .sources first, then sources.list).
mirror() {
    local uri=""
    for f in /etc/apt/sources.list.d/*.sources; do
        [ -e "$f" ] || continue
        uri="$(awk '/^URIs:/ && $2 !~ /security/ {print $2; exit}' "$f")"
        [ -n "$uri" ] && break
    done
    if [ -z "$uri" ] && [ -e /etc/apt/sources.list ]; then
        uri="$(awk '$1 == "deb" && $0 !~ /security/ {for (i = 2; i <= NF; i++) if ($i ~ /^https?:/) {print $i; exit}}' /etc/apt/sources.list)"
    fi
    echo "${uri:-http://deb.debian.org/debian}"
}

base_image() {
    local url key tag
    url="$(mirror)"
    key="$(printf '%s\n' "$suite" "$include" "$url" "$(date +%Y-%m)" | sha256sum | cut -c1-12)"
    tag="localhost/rig-base:$suite-$key"
    (
        flock 9
        if ! pod image exists "$tag"; then
            local dir
            dir="$(mktemp -d "$cache/rootfs.XXXXXX")"
            trap 'rm -rf "$dir"' EXIT
            echo "container-image: debootstrap $suite from $url (once per month)" >&2
            /usr/sbin/debootstrap --variant=minbase --include="$include" "$suite" "$dir" \
                "$url" > "$cache/debootstrap.log" 2>&1 \
                || { tail -n 20 "$cache/debootstrap.log" >&2; exit 1; }
            tar -C "$dir" -c . | pod import - "$tag" >/dev/null
            for old in $(pod images --format '{{.Repository}}:{{.Tag}}' localhost/rig-base); do
                [ "$old" = "$tag" ] || pod rmi "$old" >/dev/null 2>&1 || true
            done
        fi
    ) 9> "$cache/base.lock"
    echo "$tag"
}

cmd="${1:-build}"
shift || true
case "$cmd" in
    build)
        tag="${1:-localhost/rig:latest}"
        base="$(base_image)"
        mounts=(-v /etc/ssl/certs:/etc/ssl/certs:ro)
        [ -e /etc/pip.conf ] && mounts+=(-v /etc/pip.conf:/etc/pip.conf:ro)
        # the build stage gets a tag of its own: its layers are the cache of the next
        # build (the dependencies), and pruning untagged images keeps them
        stage_tag="${tag%:*}-build:${tag##*:}"
        [ "$stage_tag" != "$tag" ] || stage_tag="$tag-build"
        (
            flock 9
            for target in build final; do
                args=(--network host --build-arg "BASE=$base" "${mounts[@]}")
                if [ "$target" = build ]; then
                    args+=(--target build -t "$stage_tag")
                else
                    args+=(-t "$tag")
                fi
                pod build "${args[@]}" -f "$root/Dockerfile" "$root" >&2
            done
            pod image prune -f >/dev/null 2>&1 || true     # what earlier builds left
        ) 9> "$cache/build.lock"
        echo "$tag"
        ;;
    run)
        tag="$1"
        shift
        exec_args=(run --rm --network none "$tag" "$@")
        pod "${exec_args[@]}"
        ;;
    podman)
        pod "$@"
        ;;
    *)
        echo "usage: $0 build [TAG] | run TAG [ARG...] | podman [ARG...]" >&2
        exit 2
        ;;
esac
