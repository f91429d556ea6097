"""The service's helper processes (optimizer, decoder): their lifecycle follows the service."""

from __future__ import annotations

import os
import signal
import threading
import time


def child_process_init(parent_pid: int, nice: int = 0) -> None:
    """Initializer of a helper process (``ProcessPoolExecutor(initializer=...)``).

    The service owns its lifecycle: SIGINT / SIGTERM (e.g. Ctrl-C to the process group) are
    ignored, and the process exits as soon as ``parent_pid`` is gone, even after a SIGKILL of
    the service (checked every second). ``nice``: added to the process's niceness
    (``ProcessConfig.optimizer_nice``)."""
    if nice:
        os.nice(nice)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(1.0)
        os._exit(0)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()
