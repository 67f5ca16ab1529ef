"""The processes a local sweep runs (``--jobs N``): started and stopped together (:class:`Children`), and where no
progress bar can be drawn, one line a finished run (:class:`RunLines`). Torch-free."""

from __future__ import annotations

import contextlib
import subprocess
import time
from typing import Any, Iterator


class Children:
    """The ``distilkit run`` processes a sweep started: none is started once stopping began, and :meth:`stop` asks
    every live one to stop (SIGTERM: it finishes its step, writes ``last.pt`` and exits) and waits for them."""

    def __init__(self) -> None:
        import threading

        self.lock = threading.Lock()
        self.live: set[subprocess.Popen] = set()
        self.stopping = False

    def run(self, argv: list[str], **kwargs: Any) -> int | None:
        """The exit status of ``argv`` run to its end (None: not started, the sweep is stopping)."""
        with self.lock:
            if self.stopping:
                return None
            proc = subprocess.Popen(argv, **kwargs)
            self.live.add(proc)
        try:
            return proc.wait()
        finally:
            with self.lock:
                self.live.discard(proc)

    def stop(self, timeout: float = 600.0) -> None:
        import signal

        with self.lock:
            self.stopping = True
            live = list(self.live)
        for proc in live:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        for proc in live:
            try:
                proc.wait(timeout)
            except subprocess.TimeoutExpired:
                proc.kill()

    @contextlib.contextmanager
    def forwarding_sigterm(self) -> Iterator[None]:
        """SIGTERM to the sweep stops its runs as Ctrl-C does (in the main thread: KeyboardInterrupt)."""
        import signal
        import threading

        if threading.current_thread() is not threading.main_thread():
            yield
            return

        def on_term(signum: int, frame: Any) -> None:
            raise KeyboardInterrupt

        previous = signal.signal(signal.SIGTERM, on_term)
        try:
            yield
        finally:
            signal.signal(signal.SIGTERM, previous)


class RunLines:
    """One line a finished run where no progress bar can be drawn (a sweep's output sent to a file: ``nohup``, a
    Slurm job's log): which run, how long it took, how many are left and when the rest should end at the pace so
    far (the wall-clock time per finished run, so parallel jobs are counted)."""

    def __init__(self, total: int, console: Any, enabled: bool) -> None:
        self.total, self.console, self.enabled = total, console, enabled
        self.count, self.start = 0, time.monotonic()

    def done(self, title: str, seconds: float, failed: bool = False) -> str:
        self.count += 1
        left = self.total - self.count
        elapsed = time.monotonic() - self.start
        line = (f"[{self.count}/{self.total}] {title}: {'failed' if failed else 'finished'} in {span(seconds)}; "
                + (f"{left} left, about {span(elapsed / self.count * left)} more at this pace" if left else
                   f"all {self.total} done in {span(elapsed)}"))
        if self.enabled:
            self.console.print(line, highlight=False, markup=False)
        return line


def span(seconds: float) -> str:
    """``95 s``, ``12 min``, ``3 h 20 min``."""
    if seconds < 100:
        return f"{seconds:.0f} s"
    minutes = round(seconds / 60)
    return f"{minutes} min" if minutes < 60 else f"{minutes // 60} h {minutes % 60:02d} min"


__all__ = ["Children", "RunLines", "span"]
