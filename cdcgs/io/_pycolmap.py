"""pycolmap, imported once, with SIGTERM left as it was.

pycolmap's glog installs crash handlers when it loads, SIGTERM among them: a scheduler's SIGTERM
then prints a stack trace and aborts the process, and a training could not stop cleanly on it
(cdcgs.train.interrupt). The handler of SIGTERM from before the import is put back; the crash
signals (SIGSEGV, SIGABRT, ...) keep glog's stack traces. Import pycolmap through here, and after
PIL (see cdcgs/io/colmap.py).
"""

import signal
import threading

__all__ = ["import_pycolmap"]


def import_pycolmap():
    main = threading.current_thread() is threading.main_thread()
    previous = signal.getsignal(signal.SIGTERM) if main else None
    import pycolmap

    if main and previous is not None:
        signal.signal(signal.SIGTERM, previous)  # Python's own record: the handler from before the import
    return pycolmap
