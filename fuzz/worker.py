"""The fuzz harness's disposable child: runs echoloc commands in-process, one per request.

Requests arrive on stdin as JSON lines ``{"argv": [...], "cwd": "..."}``; each answer goes
to the file descriptor named on the command line as one JSON line: the exit code, what
the command wrote to stderr, its wall time and the case's peak resident memory. The
command's own stdout is captured and dropped. Running in-process keeps a case at
milliseconds instead of the CLI's 1.6 s start-up; the parent (:mod:`harness`) kills and
replaces this process when a case hangs or grows past its memory bound.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import resource
import sys
import time
import traceback
import warnings


def _exit_code(code: object) -> int:
    """What the shell would see for ``sys.exit(code)``."""
    if code is None:
        return 0
    if isinstance(code, int):
        return code
    return 1  # sys.exit("message") prints the message and exits 1


def _head_and_tail(text: str, keep: int = 2000) -> str:
    """The first and last ``keep`` characters of ``text`` (the error line and any traceback's end)."""
    return text if len(text) <= 2 * keep else text[:keep] + "\n[...]\n" + text[-keep:]


def _reset_peak_rss() -> None:
    """Start a new peak of resident memory (Linux: "5" to clear_refs resets VmHWM), so
    that a case is judged by its own peak, not by the kernels' compilation before it."""
    try:
        with open("/proc/self/clear_refs", "w") as clear:
            clear.write("5")
    except OSError:
        pass  # elsewhere ru_maxrss, the process's peak so far, stands in


def _peak_rss_kib() -> int:
    """The peak resident memory since :func:`_reset_peak_rss`, KiB."""
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1])
    except OSError:
        pass
    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)  # KiB on Linux


def run_case(argv: list[str]) -> dict[str, object]:
    """Run ``echoloc ARGV`` as the console script does; the outcome as a JSON-ready dict."""
    from echoloc.cli.commands import main

    _reset_peak_rss()
    children_before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    out, err = io.StringIO(), io.StringIO()
    start = time.perf_counter()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), warnings.catch_warnings():
        warnings.simplefilter("default")  # every distinct warning reaches stderr, as for a user
        try:
            main(argv)
            code = 0
        except SystemExit as request:
            code = _exit_code(request.code)
        except BaseException:  # what escaped cli.main: the shell would see a traceback and exit 1
            traceback.print_exc(file=err)
            code = 1
    peak_kib = _peak_rss_kib()
    # The HDF5 reader runs in a child process: its peak counts too. RUSAGE_CHILDREN keeps the
    # largest child's peak over the worker's life, so a case is charged only for a new one.
    children_after = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    if children_after > children_before:
        peak_kib += children_after  # an upper bound: the two peaks need not coincide
    return {
        "exit": code,
        "stderr": _head_and_tail(err.getvalue()),
        "seconds": time.perf_counter() - start,
        "peak_rss_bytes": peak_kib * 1024,
    }


def main() -> None:
    answers = os.fdopen(int(sys.argv[1]), "w", buffering=1)
    import echoloc.cli.commands  # noqa: F401  (imported before the first request, outside its timing)

    answers.write(json.dumps({"ready": True}) + "\n")
    for line in sys.stdin:
        request = json.loads(line)
        os.chdir(request["cwd"])
        answers.write(json.dumps(run_case(request["argv"])) + "\n")


if __name__ == "__main__":
    main()
