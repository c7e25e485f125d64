#!/usr/bin/env bash
# Run the real-SocketCAN end-to-end suite (tests/socketcan) on a real vcan0.
#
#   bash tests/socketcan/run.sh [PYTEST ARGS...]        (what `make test` / `make socketcan` run)
#
# 1. native: if this kernel has CAN (AF_CAN) and vcan0 exists or can be created (a rig
#    computer, a laptop with `modprobe vcan`), pytest runs here directly;
# 2. user-mode-linux: otherwise a Linux 6.1 UML kernel boots as an ordinary process with this
#    machine's `/` as its root (hostfs), loads vcan/can-raw/can-bcm, creates vcan0/vcan1 and
#    runs the suite inside (tests/socketcan/uml_init.sh); the Debian packages it needs
#    (user-mode-linux kmod can-utils iproute2) are installed when missing (root + apt-get);
#    on a host whose XSAVE area is larger than UML 6.1's own (AMX), UML runs with the
#    xstate fix preloaded (tests/socketcan/uml_xstate_fix.c, compiled into build/socketcan/
#    on first use; docs/socketcan.md);
# 3. neither: a loud banner and exit status 1 -- or 0 if SOCKETCAN_ALLOW_SKIP=1.
# The first line says which of these runs here.
#
# Environment: SOCKETCAN_MODE=auto|native|uml (default auto), SOCKETCAN_TIMEOUT_S (guest
# time limit, default 900), SOCKETCAN_UML_MEM (default 3G), SOCKETCAN_ALLOW_SKIP=1,
# SOCKETCAN_XSTATE_FIX=auto|on|off (default auto: preload the fix when the host needs it).
# Exit status: the suite's (pytest's) exit status; 1 on any infrastructure failure.
set -uo pipefail

here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
repo=$(cd "$here/../.." && pwd)
py="$repo/.venv/bin/python"
mode=${SOCKETCAN_MODE:-auto}
timeout_s=${SOCKETCAN_TIMEOUT_S:-900}
uml_mem=${SOCKETCAN_UML_MEM:-3G}
# the UML kernel and its module tree (Debian's user-mode-linux; tests substitute a fake)
uml_kernel=${SOCKETCAN_UML_KERNEL:-linux}
uml_modules_root=${SOCKETCAN_UML_MODULES:-/usr/lib/uml/modules}
started=$(date +%s)

say() { echo "socketcan: $*"; }
elapsed() { echo "$(( $(date +%s) - started )) s"; }

skip_or_fail() {  # skip_or_fail REASON
    echo "########################################################################" >&2
    echo "##  SocketCAN END-TO-END SUITE NOT RUN" >&2
    echo "##  reason: $1" >&2
    if [[ ${SOCKETCAN_ALLOW_SKIP:-0} == 1 ]]; then
        echo "##  SOCKETCAN_ALLOW_SKIP=1: exiting 0 although nothing was tested" >&2
        echo "########################################################################" >&2
        exit 0
    fi
    echo "##  failing (set SOCKETCAN_ALLOW_SKIP=1 to allow skipping)" >&2
    echo "########################################################################" >&2
    exit 1
}

[[ -x $py ]] || skip_or_fail "$py missing: run \`make test\` or \`make socketcan\` (creates .venv)"

# ---------------------------------------------------------------------------------- native
host_has_af_can() {
    "$py" -c 'import socket; socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()' \
        2>/dev/null
}

created_vcan=()
cleanup_native() {
    for dev in "${created_vcan[@]}"; do ip link del dev "$dev" 2>/dev/null; done
}

native_vcan_ready() {  # vcan0 exists (and is up) or we may create it
    host_has_af_can || return 1
    local dev
    for dev in vcan0 vcan1; do
        if ! ip link show "$dev" >/dev/null 2>&1; then
            { modprobe vcan 2>/dev/null; ip link add dev "$dev" type vcan 2>/dev/null; } \
                && created_vcan+=("$dev") || { [[ $dev == vcan0 ]] && return 1; continue; }
        fi
        ip link set up "$dev" 2>/dev/null || true
    done
    ip link show vcan0 | grep -q 'UP' || return 1
}

run_native() {
    trap cleanup_native EXIT
    say "runs natively on this kernel's vcan0 ($(uname -r))"
    (cd "$repo" && "$py" -m pytest tests/socketcan -q -p no:cacheprovider -rA "$@")
    local rc=$?
    say "suite exit status $rc, wall time $(elapsed)"
    exit "$rc"
}

# ------------------------------------------------------------------------ user-mode-linux
uml_modules_dir() {  # the module tree matching the UML kernel's version
    local ver
    ver=$("$uml_kernel" --version 2>/dev/null | head -n1 | tr -d '[:space:]')
    [[ -n $ver && -d $uml_modules_root/$ver ]] && echo "$uml_modules_root/$ver"
}

uml_tools_present() {
    command -v "$uml_kernel" >/dev/null && command -v modprobe >/dev/null \
        && command -v candump >/dev/null && command -v cansend >/dev/null \
        && command -v ip >/dev/null && [[ -n $(uml_modules_dir) ]]
}

install_uml_tools() {  # idempotent; apt-get update only when the install needs it
    uml_tools_present && return 0
    [[ $(id -u) == 0 ]] && command -v apt-get >/dev/null || return 1
    local pkgs=(user-mode-linux kmod can-utils iproute2) log
    log=$(mktemp)
    say "installing ${pkgs[*]} (Debian packages)"
    export DEBIAN_FRONTEND=noninteractive
    if ! apt-get install -y -qq --no-install-recommends "${pkgs[@]}" >"$log" 2>&1; then
        apt-get update -qq >>"$log" 2>&1
        apt-get install -y -qq --no-install-recommends "${pkgs[@]}" >>"$log" 2>&1 \
            || { cat "$log" >&2; rm -f "$log"; return 1; }
    fi
    rm -f "$log"
    uml_tools_present
}

# UML 6.1 writes a guest process's FPU state back with PTRACE_SETREGSET(NT_X86_XSTATE) from
# an area of its own of this many bytes; the host kernel refuses a write shorter than its
# own XSAVE size (EFAULT), so on a host with a larger area (AMX: 11,008 bytes) UML panics
# at boot ("ptrace set fp regs failed, errno = 14") unless the xstate fix is preloaded.
uml_xstate_bytes=2696
xstate_src="$here/uml_xstate_fix.c"
xstate_build=${SOCKETCAN_BUILD_DIR:-$repo/build/socketcan}  # not committed (.gitignore)
xstate_lib="$xstate_build/libuml_xstate_fix.so"
xstate_probe="$xstate_build/uml_xstate_probe"

build_xstate_fix() {  # compile the preload library and its probe when missing or stale
    [[ -x $xstate_probe && -f $xstate_lib && $xstate_probe -nt $xstate_src
       && $xstate_lib -nt $xstate_src ]] && return 0
    command -v gcc >/dev/null || { echo "gcc not found" >&2; return 1; }
    mkdir -p "$xstate_build" || return 1
    gcc -O2 -Wall -shared -fPIC -o "$xstate_lib.tmp" "$xstate_src" -ldl \
        && gcc -O2 -Wall -DXSTATE_PROBE -o "$xstate_probe.tmp" "$xstate_src" \
        && mv "$xstate_lib.tmp" "$xstate_lib" && mv "$xstate_probe.tmp" "$xstate_probe"
}

host_xstate_bytes=""
xstate_fix=0
decide_xstate_fix() {  # sets xstate_fix=1 when UML needs the fix here (or it is forced)
    local want=${SOCKETCAN_XSTATE_FIX:-auto}
    [[ $want == off ]] && return 0
    if ! build_xstate_fix; then
        [[ $want == on ]] && skip_or_fail "SOCKETCAN_XSTATE_FIX=on but the fix did not build"
        say "warning: the xstate fix did not build; UML may panic on a large-XSAVE host"
        return 0
    fi
    host_xstate_bytes=$("$xstate_probe" 2>/dev/null)
    if [[ $want == on ]] || { [[ -n $host_xstate_bytes ]] \
            && ((host_xstate_bytes > uml_xstate_bytes)); }; then
        xstate_fix=1
    fi
}

uml_way() {  # the first line of a UML run
    local ver
    ver=$("$uml_kernel" --version 2>/dev/null | head -n1 | tr -d '[:space:]')
    if ((xstate_fix)) && [[ ${SOCKETCAN_XSTATE_FIX:-auto} == on ]]; then
        echo "runs in user-mode-linux ${ver:-6.1} with the xstate fix (SOCKETCAN_XSTATE_FIX=on;" \
             "host XSAVE area ${host_xstate_bytes:-?} B, UML's $uml_xstate_bytes B)"
    elif ((xstate_fix)); then
        echo "runs in user-mode-linux ${ver:-6.1} with the xstate fix (host XSAVE area" \
             "${host_xstate_bytes:-?} B > UML's $uml_xstate_bytes B)"
    else
        echo "runs in user-mode-linux ${ver:-6.1} (host XSAVE area ${host_xstate_bytes:-?} B:" \
             "no xstate fix needed)"
    fi
}

uml_pid=""
run_dir=""
restore_max_map_count=""
cleanup_uml() {
    if [[ -n $uml_pid ]] && kill -0 "$uml_pid" 2>/dev/null; then
        # UML was started with setsid: its helper processes share its process group.
        kill -KILL -- "-$uml_pid" 2>/dev/null || kill -KILL "$uml_pid" 2>/dev/null
    fi
    [[ -n $restore_max_map_count ]] \
        && sysctl -q -w vm.max_map_count="$restore_max_map_count" 2>/dev/null
    [[ -n $run_dir && ${SOCKETCAN_KEEP_RUN_DIR:-0} != 1 ]] && rm -rf "$run_dir"
}

run_uml() {
    local modules
    modules=$(uml_modules_dir)
    run_dir=$(mktemp -d "${TMPDIR:-/tmp}/socketcan-uml.XXXXXX")
    trap cleanup_uml EXIT
    trap 'exit 130' INT TERM
    mkdir -p "$run_dir/lib/modules"
    ln -s "$modules" "$run_dir/lib/modules/$(basename "$modules")"
    # pytest arguments for the guest, NUL-separated (the kernel command line cannot quote)
    if (($#)); then printf '%s\0' "$@" > "$run_dir/pytest_args"; fi
    [[ ${SOCKETCAN_KEEP_RUN_DIR:-0} == 1 ]] && touch "$run_dir/keep"
    case "$repo$run_dir" in *[[:space:]]*)
        skip_or_fail "paths with blanks cannot go on the UML kernel command line: $repo";;
    esac

    # UML maps the guest processes' pages into its host processes one mapping at a time:
    # the kernel default of 65530 mappings per process runs out with a 3 GB guest ("UML ran
    # out of memory on the host side"); raised for the run where we may (root)
    local maps
    maps=$(sysctl -n vm.max_map_count 2>/dev/null || echo 0)
    if ((maps < 262144)) && [[ $(id -u) == 0 ]]; then
        sysctl -q -w vm.max_map_count=262144 2>/dev/null \
            && restore_max_map_count=$maps \
            && say "vm.max_map_count raised from $maps to 262144 for the guest (restored after)"
    fi
    say "booting user-mode-linux $(basename "$modules") (mem=$uml_mem, limit ${timeout_s} s)"
    local preload=()
    ((xstate_fix)) && preload=(env "LD_PRELOAD=$xstate_lib")
    # uml_dir: UML's per-run files (pid, mconsole socket) go into the run directory, not
    # ~/.uml, so a crashed guest leaves nothing behind.  `quiet` keeps the kernel's errors
    # and a panic in console.log (shown when the guest writes no exit code).
    mkdir -p "$run_dir/uml"
    setsid "${preload[@]}" "$uml_kernel" mem="$uml_mem" root=/dev/root rootfstype=hostfs rootflags=/ rw \
        init="$here/uml_init.sh" quiet con=null con0=null,fd:1 \
        uml_dir="$run_dir/uml" umid=socketcan \
        SOCKETCAN_REPO="$repo" SOCKETCAN_RUN_DIR="$run_dir" \
        > "$run_dir/console.log" 2>&1 < /dev/null &
    uml_pid=$!

    local shown=0 lines
    while kill -0 "$uml_pid" 2>/dev/null; do
        if [[ -f $run_dir/guest.log ]]; then  # stream the guest's output as it comes
            lines=$(wc -l < "$run_dir/guest.log")
            if ((lines > shown)); then
                sed -n "$((shown + 1)),${lines}p" "$run_dir/guest.log"
                shown=$lines
            fi
        fi
        if (( $(date +%s) - started > timeout_s )); then
            say "TIMEOUT after ${timeout_s} s: killing user-mode-linux (pid $uml_pid)"
            kill -KILL -- "-$uml_pid" 2>/dev/null || kill -KILL "$uml_pid" 2>/dev/null
            break
        fi
        sleep 1
    done
    wait "$uml_pid" 2>/dev/null
    [[ -f $run_dir/guest.log ]] && sed -n "$((shown + 1)),\$p" "$run_dir/guest.log"

    if [[ ! -s $run_dir/exit_code ]]; then
        say "the guest wrote no exit code: FAILED. The kernel's own words:"
        grep -a -m 12 -i -E 'panic|ptrace|errno|fatal|oops|bug:|failed|killed' \
            "$run_dir/console.log" | sed 's/^/    /'
        say "UML console (last 25 lines):"
        tail -n 25 "$run_dir/console.log" | sed 's/^/    /'
        ((xstate_fix)) || say "hint: a large-XSAVE host needs the xstate fix" \
            "(SOCKETCAN_XSTATE_FIX=on; docs/socketcan.md)"
        say "wall time $(elapsed)"
        exit 1
    fi
    local rc
    rc=$(tr -dc '0-9' < "$run_dir/exit_code")
    say "suite exit status ${rc:-?} (inside user-mode-linux), wall time $(elapsed)"
    exit "${rc:-1}"
}

# ------------------------------------------------------------------------------- dispatch
case $mode in
    native)
        native_vcan_ready || skip_or_fail "SOCKETCAN_MODE=native but vcan0 is not available"
        run_native "$@";;
    uml)
        decide_xstate_fix
        say "$(uml_way)"
        install_uml_tools || skip_or_fail "user-mode-linux not available and not installable"
        run_uml "$@";;
    auto)
        if native_vcan_ready; then run_native "$@"; fi
        decide_xstate_fix
        say "$(uml_way)"
        if install_uml_tools; then run_uml "$@"; fi
        skip_or_fail "no vcan on this kernel ($(uname -r)) and user-mode-linux is not \
available (needs Debian's user-mode-linux kmod can-utils iproute2; install as root)";;
    *)
        skip_or_fail "SOCKETCAN_MODE=$mode (expected auto, native or uml)";;
esac
