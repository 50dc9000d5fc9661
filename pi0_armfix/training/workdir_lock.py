"""One run per workdir: `<workdir>/run.lock`, held by process 0 for the run's life.

The lock is an `flock` on the file, so the kernel drops it when its holder dies (a killed run
leaves no stale lock to clean up); the file's text (host, pid, start time) only names the holder
in the message a second run gets. A second run on a held workdir stops at once, before touching
its checkpoints or `metrics.jsonl`. flock works across processes of one host and on most
shared file systems (NFS v4, Lustre with flock enabled); where it does not, nothing is locked.
"""

from __future__ import annotations

import fcntl
import json
import os
import socket
import time
from typing import IO

from etils import epath

LOCK_FILE = "run.lock"


def lock_workdir(workdir: epath.Path) -> IO[str]:
    """Takes the workdir's lock; returns the open lock file (closing it releases the lock).

    Raises:
      ValueError naming the holder (host, pid, start) when another run holds it.
    """
    path = epath.Path(workdir) / LOCK_FILE
    handle = open(path, "a+")
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.seek(0)
        holder = handle.read().strip() or "{}"
        handle.close()
        try:
            who = json.loads(holder)
            named = (f"pid {who.get('pid')} on host {who.get('host')} since "
                     f"{who.get('started')}")
        except json.JSONDecodeError:
            named = "another process"
        raise ValueError(f"workdir {workdir} is in use by a run ({named}): wait for it to end, "
                         "or train in another --workdir") from None
    except OSError:  # a file system without flock: run unlocked rather than not at all
        return handle
    handle.seek(0)
    handle.truncate()
    handle.write(json.dumps({"host": socket.gethostname(), "pid": os.getpid(),
                             "started": time.strftime("%Y-%m-%d %H:%M:%S")}))
    handle.flush()
    return handle
