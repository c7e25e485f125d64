/*
 * uml_xstate_fix.c -- lets Debian's user-mode-linux 6.1 boot on hosts with a large XSAVE
 * area (AMX: 11,008 bytes), for tests/socketcan/run.sh.
 *
 * Why: UML keeps each guest process's FPU state in a fixed area of its own (2,696 bytes
 * in 6.1) and writes it back with ptrace(PTRACE_SETREGSET, pid, NT_X86_XSTATE, iov).  The
 * host kernel accepts that write only when iov_len is exactly the host's full user XSAVE
 * size (arch/x86/kernel/fpu/regset.c: xstateregs_set; a longer buffer is cut to that size
 * first, a shorter one is refused with EFAULT).  Where the host's area is larger than
 * UML's, every write fails, and UML panics at boot with "userspace - ptrace set fp regs
 * failed, errno = 14".  Mainline UML fixed this in v6.13 ("um: switch to regset API and
 * depend on XSTATE", 3f17fed21491); Debian bookworm has no newer UML.
 *
 * What: an LD_PRELOAD library for the `linux` binary that wraps ptrace().  A
 * PTRACE_SETREGSET of NT_X86_XSTATE shorter than the host's size is sent as a buffer of
 * the host's size: UML's bytes first, the rest the tracee's current state (read with
 * PTRACE_GETREGSET).  Every other call, and a write of the host's size or longer, goes to
 * glibc's ptrace unchanged, so the library does nothing on a host that does not need it.
 *
 * Built with -DXSTATE_PROBE, the same file is a probe for run.sh and the tests:
 *   uml_xstate_probe             prints the host's XSAVE size in bytes
 *   uml_xstate_probe --set N     writes the first N bytes of a stopped child's XSAVE area
 *                                with xmm0 changed, then checks that xmm0 took the new
 *                                value and every byte past N is unchanged; exit 0 if so,
 *                                1 with errno's name if the write failed
 */
#define _GNU_SOURCE
#include <dlfcn.h>
#include <elf.h>
#include <errno.h>
#include <signal.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/ptrace.h>
#include <sys/syscall.h>
#include <sys/types.h>
#include <sys/uio.h>
#include <sys/wait.h>
#include <unistd.h>

#ifndef NT_X86_XSTATE
#define NT_X86_XSTATE 0x202
#endif

/* Larger than any XSAVE area the x86 architecture defines today (AMX: 11,008 bytes). */
#define XSTATE_PROBE_BYTES (64 * 1024)

#ifndef XSTATE_PROBE
/* The host's full user XSAVE size: a PTRACE_GETREGSET with a large buffer is cut by the
 * kernel to the regset's size, and iov_len says how much it wrote.  0 if it fails. */
static size_t host_xstate_bytes(pid_t pid) {
    static size_t cached;
    if (cached) return cached;
    void *buf = malloc(XSTATE_PROBE_BYTES);
    if (!buf) return 0;
    struct iovec iov = {buf, XSTATE_PROBE_BYTES};
    if (syscall(SYS_ptrace, PTRACE_GETREGSET, pid, (void *)NT_X86_XSTATE, &iov) == 0)
        cached = iov.iov_len;
    free(buf);
    return cached;
}

typedef long (*ptrace_fn)(enum __ptrace_request, ...);

static long set_xstate_padded(pid_t pid, const struct iovec *short_iov, size_t host) {
    unsigned char *buf = malloc(host);
    if (!buf) { errno = ENOMEM; return -1; }
    struct iovec iov = {buf, host};
    long rc = syscall(SYS_ptrace, PTRACE_GETREGSET, pid, (void *)NT_X86_XSTATE, &iov);
    if (rc == 0 && iov.iov_len == host) {
        memcpy(buf, short_iov->iov_base, short_iov->iov_len);
        rc = syscall(SYS_ptrace, PTRACE_SETREGSET, pid, (void *)NT_X86_XSTATE, &iov);
    } else if (rc == 0) {
        errno = EFAULT;
        rc = -1;
    }
    int saved = errno;
    free(buf);
    errno = saved;
    return rc;
}

long ptrace(enum __ptrace_request request, ...) {
    static ptrace_fn real_ptrace;
    va_list ap;
    va_start(ap, request);
    pid_t pid = va_arg(ap, pid_t);
    void *addr = va_arg(ap, void *);
    void *data = va_arg(ap, void *);
    va_end(ap);
    if (request == PTRACE_SETREGSET && (unsigned long)addr == NT_X86_XSTATE && data) {
        const struct iovec *iov = data;
        size_t host = host_xstate_bytes(pid);
        if (host && iov->iov_len < host) return set_xstate_padded(pid, iov, host);
    }
    if (!real_ptrace) real_ptrace = (ptrace_fn)dlsym(RTLD_NEXT, "ptrace");
    if (!real_ptrace) { errno = ENOSYS; return -1; }
    return real_ptrace(request, pid, addr, data);
}

#else  /* XSTATE_PROBE: glibc's ptrace, or the library's where it is preloaded */
/* xmm0 in the standard-format XSAVE area (the legacy FXSAVE region's byte 160). */
#define XMM0_OFFSET 160

static pid_t stopped_child(void) {
    pid_t pid = fork();
    if (pid == 0) {
        ptrace(PTRACE_TRACEME, 0, NULL, NULL);
        raise(SIGSTOP);
        _exit(0);
    }
    int status;
    if (pid < 0 || waitpid(pid, &status, 0) != pid || !WIFSTOPPED(status)) return -1;
    return pid;
}

static int get_all(pid_t pid, unsigned char *buf, size_t *bytes) {
    struct iovec iov = {buf, XSTATE_PROBE_BYTES};
    if (ptrace(PTRACE_GETREGSET, pid, (void *)NT_X86_XSTATE, &iov) != 0) return -1;
    *bytes = iov.iov_len;
    return 0;
}

int main(int argc, char **argv) {
    pid_t pid = stopped_child();
    if (pid < 0) { perror("uml_xstate_probe: ptrace child"); return 2; }
    static unsigned char before[XSTATE_PROBE_BYTES], after[XSTATE_PROBE_BYTES];
    size_t host = 0, again = 0;
    int rc = 0;
    if (get_all(pid, before, &host) != 0) {
        perror("uml_xstate_probe: PTRACE_GETREGSET");
        rc = 2;
    } else if (argc == 1) {
        printf("%zu\n", host);
    } else if (argc == 3 && strcmp(argv[1], "--set") == 0) {
        size_t n = strtoul(argv[2], NULL, 10);
        unsigned char *part = malloc(n);
        memcpy(part, before, n < host ? n : host);
        if (n > host) memset(part + host, 0, n - host);
        for (int i = 0; i < 16; i++) part[XMM0_OFFSET + i] = (unsigned char)(0xA5 ^ i);
        struct iovec iov = {part, n};
        if (ptrace(PTRACE_SETREGSET, pid, (void *)NT_X86_XSTATE, &iov) != 0) {
            printf("set %zu of %zu bytes: %s\n", n, host, strerrorname_np(errno));
            rc = 1;
        } else if (get_all(pid, after, &again) != 0 || again != host) {
            printf("set %zu of %zu bytes: state unreadable afterwards\n", n, host);
            rc = 3;
        } else if (memcmp(after + XMM0_OFFSET, part + XMM0_OFFSET, 16) != 0) {
            printf("set %zu of %zu bytes: xmm0 did not take the new value\n", n, host);
            rc = 3;
        } else if (n < host && memcmp(after + n, before + n, host - n) != 0) {
            printf("set %zu of %zu bytes: bytes past %zu changed\n", n, host, n);
            rc = 3;
        } else {
            printf("set %zu of %zu bytes: ok\n", n, host);
        }
        free(part);
    } else {
        fprintf(stderr, "usage: uml_xstate_probe [--set BYTES]\n");
        rc = 2;
    }
    kill(pid, SIGKILL);
    waitpid(pid, NULL, 0);
    return rc;
}
#endif
