#!/usr/bin/env bash
# Install the Debian packages the test suite uses, if missing (idempotent, quiet).
#   systemd   -> systemd-analyze (unit security/verify tests), libseccomp
#   openssl   -> throw-away certificates for the Zenoh TLS test
#   iproute2  -> `ip link` for vcan set-up
#   chromium  -> renders the HTML run report in a real browser
#   rt-tests  -> cyclictest, run next to `rig check-host` (rig/rt/cyclictest.py)
#   podman, runc, debootstrap -> build and run the container image
#               (scripts/container-image.sh, tests/test_deploy.py)
# Usage: scripts/ensure-debian-packages.sh [package ...]   (defaults to the list above)
# Does nothing (and says so) where apt-get is not available or we are not root.
set -euo pipefail
pkgs=("$@")
[ ${#pkgs[@]} -gt 0 ] || pkgs=(systemd openssl iproute2 chromium rt-tests podman runc debootstrap)
missing=()
for p in "${pkgs[@]}"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
[ ${#missing[@]} -eq 0 ] && exit 0
if ! command -v apt-get >/dev/null 2>&1 || [ "$(id -u)" -ne 0 ]; then
    echo "ensure-debian-packages: cannot install ${missing[*]} (need Debian and root);" \
         "the tests that need them will skip and say why" >&2
    exit 0
fi
echo "ensure-debian-packages: installing ${missing[*]}" >&2
export DEBIAN_FRONTEND=noninteractive
apt-get update -qq >/dev/null
apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
