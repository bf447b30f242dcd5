"""Runs a module as a process of a local cluster that dies with the process that started it:
``python die_with_parent.py PARENT_PID MODULE [ARGUMENTS ...]`` (core.distributed.engine's
LocalProcesses starts its scheduler and workers so).

Without it, a bake killed with SIGKILL (or a Blender that crashed) left every ``dask worker``
running as an orphan, each holding its cores and memory. On Linux the kernel sends the child
SIGKILL when its parent ends (prctl PR_SET_PDEATHSIG): immediate, and nothing to run in the
dying parent. The signal follows the parent *thread* that started the child, which is why
LocalProcesses is a ``with`` block (started and closed by one thread). Elsewhere a daemon
thread polls whether the parent still lives and ends the process when it does not.

A ``dask worker`` is a nanny whose worker is its own child: the nanny's end closes the pipe
that child watches (distributed.process.AsyncProcess), so the child follows within moments.

This file is run by path, not as part of a package: it imports nothing of VisiBake.
"""
import ctypes
import os
import runpy
import signal
import sys
import threading
import time

PR_SET_PDEATHSIG = 1  # <linux/prctl.h>
# How often the watchdog (off Linux) asks whether the parent lives.
POLL_SECONDS = 0.5


def _parent_alive(parent: int) -> bool:
    if os.name == "posix":
        return os.getppid() == parent  # an orphan is adopted by another process
    import psutil  # a dependency of distributed: there wherever a cluster runs

    return psutil.pid_exists(parent)


def _watch(parent: int) -> None:
    while _parent_alive(parent):
        time.sleep(POLL_SECONDS)
    os._exit(1)


def die_with(parent: int) -> None:
    """End this process when process ``parent`` ends (at once if it already has)."""
    if sys.platform.startswith("linux"):
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) != 0:
            threading.Thread(target=_watch, args=(parent,), daemon=True, name="visibake-parent-watch").start()
    else:
        threading.Thread(target=_watch, args=(parent,), daemon=True, name="visibake-parent-watch").start()
    # The parent may have ended before the signal was armed: then none will come.
    if not _parent_alive(parent):
        os._exit(1)


if __name__ == "__main__":
    die_with(int(sys.argv[1]))
    module = sys.argv[2]
    sys.argv = [module, *sys.argv[3:]]
    runpy.run_module(module, run_name="__main__", alter_sys=True)
