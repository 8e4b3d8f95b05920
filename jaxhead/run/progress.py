"""Progress of a running stage: a live line on a terminal, plain log lines otherwise.  [host]

Stages run library calls that print nothing for minutes (atlas build, registration, meshing,
Jacobians, fits). While a stage runs, a background thread reports how long it has been running:
on a terminal, one line rewritten in place every second; elsewhere (files, pipes, logs) a plain
line every `every_s` seconds; under CI (``CI=true``) nothing beyond the stage's start and end.
"""

import contextlib
import os
import sys
import threading
import time
from collections.abc import Callable, Iterator


def _clock(seconds: float) -> str:
    m, s = divmod(int(seconds), 60)
    h, m = divmod(m, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


def progress_mode(stream=None) -> str:
    """"quiet" under CI=true, "live" on a terminal, else "lines"."""
    if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
        return "quiet"
    stream = sys.stderr if stream is None else stream
    return "live" if getattr(stream, "isatty", lambda: False)() else "lines"


@contextlib.contextmanager
def heartbeat(label: str, say: Callable[[str], None], *, every_s: float = 30.0,
              mode: str | None = None, stream=None) -> Iterator[None]:
    """Report `label: still running (m:ss)` while the block runs.

    Arguments:
        label: e.g. "[mri] mesh".
        say: where plain lines go (mode "lines").
        every_s: seconds between plain lines; <= 0 turns them off.
        mode: "live", "lines" or "quiet" (default: `progress_mode()`).
        stream: the terminal for mode "live" (default: stderr).
    """
    mode = progress_mode(stream) if mode is None else mode
    stream = sys.stderr if stream is None else stream
    if mode == "quiet" or (mode == "lines" and every_s <= 0):
        yield
        return
    stop = threading.Event()
    t0 = time.monotonic()

    def beat():
        period = 1.0 if mode == "live" else every_s
        while not stop.wait(period):
            text = f"{label}: still running ({_clock(time.monotonic() - t0)})"
            if mode == "live":
                stream.write("\r" + text + "\033[K")
                stream.flush()
            else:
                say(text)

    thread = threading.Thread(target=beat, name=f"jaxhead-progress {label}", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()
        if mode == "live":
            stream.write("\r\033[K")
            stream.flush()
