"""A small, scriptable child program for tests that need real processes.

Run it as ``python -m temoto.testing.child [options]`` (build the command line with
:func:`temoto.testing.child_command`). It is what TeMoto's own Process Manager tests spawn, and
it is public: use it in your tests of code that starts, watches or stops processes.

What it does, in order:

1. disables core dumps (``RLIMIT_CORE = 0``), so ``--crash`` and ``kill SEGV`` leave no files;
2. ignores SIGTERM if ``--ignore-term`` is given;
3. prints ``ready <pid>`` as its **first line** of standard output;
4. forks ``--grandchildren N`` grandchildren. They stay in the child's process group and
   session, inherit its SIGTERM disposition, sleep until killed, and never read stdin. The child
   prints one ``grandchild <pid>`` line per grandchild (after ``ready``, in fork order), so a
   test that has read these N lines knows every grandchild exists;
5. writes its pid (one line) to ``--touch FILE``, for tests that cannot read its standard
   output. A regular file is written atomically (a temporary file renamed into place); a named
   pipe (``os.mkfifo``) is written into, so a test can block on reading it instead of polling
   for a file. When the pid arrives, steps 1-4 are done (their output is written);
6. sleeps for ``--sleep S`` seconds, then exits with ``--exit CODE`` (default 0) or aborts if
   ``--crash`` is given (SIGABRT). Without ``--sleep`` it sleeps forever, unless ``--exit`` or
   ``--crash`` is given, which then happen at once;
7. with ``--on-stdin``, while it sleeps it also reads commands from standard input, one per
   line: ``exit N`` (exit with code N), ``crash`` (abort: SIGABRT), ``kill SIG`` (send itself a
   signal, by name — ``TERM``, ``SIGSEGV`` — or number). Unknown commands are reported on
   standard error and ignored. End of input stops the reading, not the sleep.

Output lines are written with one ``write`` each, so lines never interleave. The exit codes of
the program itself: 2 for bad options (argparse), otherwise what the options asked for.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import resource
import selectors
import signal
import stat
import sys
import time

__all__ = ["main"]


def _say(line: str) -> None:
    """Write one line to standard output with a single ``write`` (atomic on pipes)."""
    with contextlib.suppress(OSError):  # stdout closed: nobody listens
        os.write(1, (line + "\n").encode())


def _parse_signal(text: str) -> int:
    text = text.strip().upper()
    if text.isdigit():
        return int(text)
    if not text.startswith("SIG"):
        text = "SIG" + text
    return int(signal.Signals[text])


def _grandchild() -> None:
    """Body of a forked grandchild: sleep until a signal ends the process."""
    with contextlib.suppress(OSError):
        os.close(0)  # never compete with the child for commands
    while True:
        signal.pause()


def _write_pid_file(path: str) -> None:
    if os.path.exists(path) and stat.S_ISFIFO(os.stat(path).st_mode):
        # A named pipe: write into it, so a test can block on reading it (no polling).
        with open(path, "w", encoding="ascii") as f:
            f.write(f"{os.getpid()}\n")
        return
    tmp = f"{path}.{os.getpid()}.tmp"
    with open(tmp, "w", encoding="ascii") as f:
        f.write(f"{os.getpid()}\n")
    os.replace(tmp, path)


def _run_command(line: str) -> None:
    words = line.split()
    if not words:
        return
    try:
        if words[0] == "exit" and len(words) == 2:
            os._exit(int(words[1]))
        elif words[0] == "crash" and len(words) == 1:
            os.abort()
        elif words[0] == "kill" and len(words) == 2:
            os.kill(os.getpid(), _parse_signal(words[1]))
            return
    except (ValueError, KeyError):
        pass
    sys.stderr.write(f"temoto.testing.child: bad command {line!r}\n")
    sys.stderr.flush()


def _sleep(seconds: float | None, on_stdin: bool) -> None:
    """Sleep for ``seconds`` (None: forever), serving stdin commands if asked."""
    deadline = None if seconds is None else time.monotonic() + seconds
    if not on_stdin:
        if deadline is None:
            while True:
                signal.pause()
        time.sleep(max(0.0, deadline - time.monotonic()))
        return
    buffer = b""
    with selectors.DefaultSelector() as sel:
        sel.register(0, selectors.EVENT_READ)
        reading = True
        while True:
            timeout = None if deadline is None else deadline - time.monotonic()
            if timeout is not None and timeout <= 0:
                return
            if not reading:
                if timeout is None:
                    while True:
                        signal.pause()
                time.sleep(timeout)
                return
            if not sel.select(timeout):
                continue
            chunk = os.read(0, 4096)
            if not chunk:
                reading = False
                sel.unregister(0)
                continue
            buffer += chunk
            while b"\n" in buffer:
                line, buffer = buffer.split(b"\n", 1)
                _run_command(line.decode(errors="replace"))


def main(argv: list[str] | None = None) -> int:
    """Run the child program.

    Args:
        argv: Command-line arguments without the program name; ``sys.argv[1:]`` if None.

    Returns:
        The exit code (when it does not abort or get killed).
    """
    parser = argparse.ArgumentParser(
        prog="python -m temoto.testing.child", description="A scriptable test child process."
    )
    parser.add_argument("--sleep", type=float, default=None, metavar="S")
    parser.add_argument("--exit", type=int, default=None, metavar="CODE", dest="exit_code")
    parser.add_argument("--crash", action="store_true")
    parser.add_argument("--ignore-term", action="store_true")
    parser.add_argument("--grandchildren", type=int, default=0, metavar="N")
    parser.add_argument("--on-stdin", action="store_true")
    parser.add_argument("--touch", default=None, metavar="FILE")
    opts = parser.parse_args(argv)
    if opts.grandchildren < 0:
        parser.error("--grandchildren must be >= 0")

    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
    if opts.ignore_term:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
    _say(f"ready {os.getpid()}")
    for _ in range(opts.grandchildren):
        pid = os.fork()
        if pid == 0:  # pragma: no cover - runs in the grandchild
            try:
                _grandchild()
            finally:
                os._exit(0)
        _say(f"grandchild {pid}")
    if opts.touch:
        _write_pid_file(opts.touch)

    seconds = opts.sleep
    if seconds is None and (opts.exit_code is not None or opts.crash):
        seconds = 0.0
    _sleep(seconds, opts.on_stdin)
    if opts.crash:
        os.abort()
    return 0 if opts.exit_code is None else int(opts.exit_code)


if __name__ == "__main__":
    sys.exit(main())
