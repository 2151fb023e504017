"""The first program of an attempt's process: tie it to the Ray worker that started it, then become the attempt.

    python .../ablations/sweep/child.py WORKER_PID PROGRAM [ARGUMENTS...]

Started by path (not ``-m``), so it imports nothing but the standard library before it execs. On Linux it asks
for SIGKILL when its parent dies (PR_SET_PDEATHSIG survives exec): a worker killed by a node's out-of-memory
killer, or a node going away, takes its run down with it instead of leaving it training unowned. SIGINT and
SIGTERM reach the attempt with their default handling, whatever the worker did with them.
"""

import ctypes
import os
import signal
import sys

_PR_SET_PDEATHSIG = 1


def main() -> None:
    parent = int(sys.argv[1])
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL))
        if os.getppid() != parent:  # the worker died before the request took effect
            sys.exit("ablate-sweep: the worker that started this run is gone")
    # A Ray worker ignores or blocks SIGINT and SIGTERM, and both survive exec: ablate would then never see the
    # signal that asks it to checkpoint and stop. Its own handlers start from the defaults.
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})
    os.execv(sys.argv[2], sys.argv[2:])


if __name__ == "__main__":
    main()
