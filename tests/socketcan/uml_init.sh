#!/bin/bash
# PID 1 of the user-mode-linux guest started by tests/socketcan/run.sh.
#
# The guest's root file system is the host's `/` (hostfs), so the repository, its .venv and
# the run directory are visible at their host paths.  run.sh passes, on the kernel command
# line (unknown `KEY=value` parameters become init's environment):
#   SOCKETCAN_REPO     absolute path of the repository
#   SOCKETCAN_RUN_DIR  host directory for this run: lib/modules -> the UML modules, and the
#                      files this script writes: `exit_code` (the suite's exit status) and
#                      `guest.log` (everything printed here)
# and it may write `pytest_args` there: extra pytest arguments, NUL-separated.
# It mounts the pseudo file systems, loads vcan/can-raw/can-bcm, creates vcan0 and vcan1,
# brings lo up (Zenoh listens on 127.0.0.1), runs the suite and powers the guest off.
# The guest cannot return an exit status to the host: `exit_code` is the only verdict.

export PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin
export HOME=/root LANG=C.UTF-8 LC_ALL=C.UTF-8 TERM=dumb
export PYTHONUNBUFFERED=1 PYTHONDONTWRITEBYTECODE=1
export SOCKETCAN_IN_UML=1

host_run_dir=${SOCKETCAN_RUN_DIR:?SOCKETCAN_RUN_DIR not set on the kernel command line}
repo=${SOCKETCAN_REPO:?SOCKETCAN_REPO not set on the kernel command line}

power_off() {
    sync
    echo o > /proc/sysrq-trigger 2>/dev/null
    poweroff -f 2>/dev/null
    halt -f -p 2>/dev/null
    sleep 5
    exit 0  # init exiting panics the UML kernel, which ends the process as well
}

# Pseudo file systems.  The run directory is bind-mounted to /run/socketcan, then /tmp
# becomes a private tmpfs: the tests' temporary files stay inside the guest (fast, and
# out of the way of pytest runs on the host, which share the host's /tmp/pytest-of-*).
mount -t proc proc /proc
mount -t sysfs sysfs /sys
# the UML kernel auto-mounts devtmpfs on /dev (CONFIG_DEVTMPFS_MOUNT); mount it if not
[[ -c /dev/null ]] || mount -t devtmpfs devtmpfs /dev
mkdir -p /dev/shm /dev/pts
mount -t tmpfs -o mode=1777 shm /dev/shm     # multiprocessing semaphores need it
mount -t devpts devpts /dev/pts
mount -t tmpfs -o mode=0755 run /run
mkdir -p /run/socketcan
python_real=$(readlink -f "$repo/.venv/bin/python")
case "$repo/ $python_real" in
    /tmp/*|*" /tmp/"*) tmp_private=0 ;;   # the repository or Python lives in /tmp: keep it
    *) tmp_private=1 ;;
esac
if ((tmp_private)) && mount --bind "$host_run_dir" /run/socketcan; then
    run_dir=/run/socketcan
    mount -t tmpfs -o mode=1777 tmp /tmp
else
    run_dir=$host_run_dir   # keep going on the shared /tmp
fi
log="$run_dir/guest.log"

verdict() {  # verdict CODE MESSAGE: record the exit status and stop the guest
    echo "uml_init: $2" | tee -a "$log"
    echo "$1" > "$run_dir/exit_code.tmp" && mv "$run_dir/exit_code.tmp" "$run_dir/exit_code"
    power_off
}

echo "uml_init: guest kernel $(uname -r), $(nproc) CPU(s), run directory $run_dir" >> "$log"
hostname uml-socketcan

{
    for m in vcan can-raw can-bcm; do
        modprobe -d "$run_dir" "$m" || exit 1
    done
    ip link set lo up
    # 8 MiB socket receive buffers (the kernel default, ~200 CAN frames, overflows in
    # the guest's stalls of up to ~1.5 s: a process would see lost frames that a rig
    # computer would not; docs/socketcan.md)
    sysctl -q -w net.core.rmem_default=8388608 net.core.rmem_max=8388608
    for dev in vcan0 vcan1; do
        ip link add dev "$dev" type vcan || exit 1
        ip link set "$dev" mtu 16           # classic CAN frames only, as on the rig
        ip link set "$dev" txqueuelen 1000  # the rig's can0 set-up uses the same
        ip link set up "$dev" || exit 1
    done
    ip -details link show vcan0
} >> "$log" 2>&1 || verdict 91 "loading the CAN modules / creating vcan0 failed"

cd "$repo" || verdict 92 "repository $repo not visible in the guest"
extra=()
[[ -f $run_dir/pytest_args ]] && mapfile -d '' -t extra < "$run_dir/pytest_args"
echo "uml_init: running the SocketCAN suite: pytest tests/socketcan ${extra[*]}" >> "$log"
"$repo/.venv/bin/python" -m pytest tests/socketcan -q -p no:cacheprovider -rA \
    "${extra[@]}" >> "$log" 2>&1
rc=$?
# run.sh with SOCKETCAN_KEEP_RUN_DIR=1: keep the tests' temporary files (captures, MCAPs,
# process logs).  They are written to the guest's tmpfs during the run (hostfs writes
# stall the non-preemptible guest kernel) and copied out here.
[[ -f $run_dir/keep ]] && cp -a /tmp/pytest-of-root "$run_dir/pytest" 2>/dev/null
verdict "$rc" "pytest finished with exit status $rc"
