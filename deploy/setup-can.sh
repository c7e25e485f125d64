#!/usr/bin/env bash
# Bring up a CAN interface for the rig by hand (when systemd-networkd is not used).
#
#   sudo deploy/setup-can.sh can0 [BITRATE] [RESTART_MS] [TXQUEUELEN]   # real adapter
#   sudo deploy/setup-can.sh vcan0                                      # bench (virtual)
#   DRY_RUN=1 deploy/setup-can.sh can0                                  # print, do nothing
#
# Needs CAP_NET_ADMIN (root).  The rig service itself needs no capability for CAN_RAW.
# Defaults: 1 Mbit/s, automatic bus-off restart after 100 ms, txqueuelen 128 (the kernel
# default of 10 frames overflows with ENOBUFS at two frames per millisecond).
set -euo pipefail

IFACE="${1:-can0}"
BITRATE="${2:-1000000}"
RESTART_MS="${3:-100}"
TXQUEUELEN="${4:-128}"

run() {
    if [[ "${DRY_RUN:-0}" == "1" ]]; then
        echo "$*"
    else
        "$@"
    fi
}

die() { echo "setup-can.sh: $*" >&2; exit 2; }

[[ "$IFACE" =~ ^[a-zA-Z0-9_.-]{1,15}$ ]] || die "bad interface name '$IFACE'"
[[ "$BITRATE" =~ ^[0-9]+$ ]] && (( BITRATE >= 10000 && BITRATE <= 1000000 )) \
    || die "bitrate '$BITRATE' must be an integer in [10000, 1000000] (classic CAN)"
[[ "$RESTART_MS" =~ ^[0-9]+$ ]] || die "restart-ms '$RESTART_MS' must be an integer >= 0"
[[ "$TXQUEUELEN" =~ ^[0-9]+$ ]] && (( TXQUEUELEN >= 1 )) \
    || die "txqueuelen '$TXQUEUELEN' must be a positive integer"

if [[ "$IFACE" == vcan* ]]; then
    run modprobe vcan
    if ! ip link show "$IFACE" >/dev/null 2>&1 || [[ "${DRY_RUN:-0}" == "1" ]]; then
        run ip link add dev "$IFACE" type vcan
    fi
    run ip link set "$IFACE" txqueuelen "$TXQUEUELEN"
    run ip link set "$IFACE" up
else
    run ip link set "$IFACE" down
    run ip link set "$IFACE" type can bitrate "$BITRATE" restart-ms "$RESTART_MS" \
        berr-reporting on
    run ip link set "$IFACE" txqueuelen "$TXQUEUELEN"
    run ip link set "$IFACE" up
fi
if [[ "${DRY_RUN:-0}" != "1" ]]; then
    ip -details -statistics link show "$IFACE"
fi
