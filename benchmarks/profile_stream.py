"""Where a streamed frame's time goes, compiled kernels by name: a sampling profile with perf.

cProfile sees a numba kernel as one opaque call and shifts time between the Python
functions around it; py-spy sees only Python. This runs the stream (`echoloc bench`'s
scene: 4 receivers x 2400 samples, ``--reflectors`` objects, one core, a frame a call)
for ``--seconds`` under Linux ``perf record``, and names the compiled code: numba's
kernels are compiled afresh, into an empty cache of its own (machine code loaded from the
cache does not list its functions; about two minutes) and their addresses written to
``/tmp/perf-PID.map``, the file perf reads JIT symbols from. Each function's share of
the samples is printed as microseconds of the measured frame time, and the shares are
summed by where they run: echoloc's kernels (each by name), the FFTs (scipy.fft's pocketfft
from Python, rocket-fft's from compiled code), the Python interpreter, numpy, libc (malloc,
memset) and the rest.

Needs ``perf`` (Debian: ``linux-perf``) and permission to profile this user's processes
(``kernel.perf_event_paranoid`` <= 2). For speed figures use ``echoloc bench``: perf's
sampling slows the frames a little.

    python benchmarks/profile_stream.py --seconds 15 --markdown benchmarks/results/profile_stream.md
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

_KERNEL_MODULES = (
    "echoloc._chain_kernels",
    "echoloc.tof._echoes_kernels",
    "echoloc.localise._locate_kernels",
    "echoloc.maps._mapping_kernels",
)


def numba_symbol(mangled: str) -> str:
    """``module.function`` of a numba-mangled echoloc name (else the name as it is)."""
    match = re.match(r"_ZN7echoloc(\d+)", mangled)
    if not match:
        return mangled
    rest = mangled[match.end() :]
    module = rest[: int(match.group(1))]
    rest = rest[int(match.group(1)) :]
    length = re.match(r"\d+", rest)
    if not length:
        return f"{module}.?"
    function = rest[length.end() : length.end() + int(length.group())]
    return f"{module}.{function}"


def perf_map_path() -> Path:
    """The file perf reads this process's JIT symbols from."""
    return Path(f"/tmp/perf-{os.getpid()}.map")


def write_perf_map() -> int:
    """Write /tmp/perf-PID.map for every compiled function of echoloc's kernel modules; how many."""
    import importlib

    entries: dict[int, str] = {}
    for name in _KERNEL_MODULES:
        module = importlib.import_module(name)
        for value in vars(module).values():
            for result in getattr(value, "overloads", {}).values():
                library = result.library
                try:
                    functions = list(library._final_module.functions)
                except Exception:  # loaded from the cache: no function list
                    continue
                for function in functions:
                    if function.is_declaration:
                        continue
                    address = library.get_pointer_to_function(function.name)
                    if address:
                        entries[address] = function.name
    addresses = sorted(entries)
    if not addresses:
        return 0
    with perf_map_path().open("w") as perf_map:
        for here, after in zip(addresses, [*addresses[1:], addresses[-1] + 4096], strict=True):
            perf_map.write(f"{here:x} {min(after - here, 1 << 20):x} {entries[here]}\n")
    return len(addresses)


def _where(dso: str, symbol: str) -> str:
    if symbol.startswith(tuple(name.removeprefix("echoloc.") + "." for name in _KERNEL_MODULES)):
        return "echoloc kernels"
    if "pocketfft" in dso or "rocket_fft" in dso:
        return "pocketfft, rocket-fft (FFT)"
    if "libpython" in dso:
        return "Python interpreter"
    if "_multiarray" in dso or "numpy" in dso:
        return "numpy"
    if dso.startswith("libc") or dso.startswith("libm"):
        return "libc, libm"
    if "NRT" in symbol or "numba" in dso or "_helperlib" in dso or "_dispatcher" in dso:
        return "numba runtime"
    return "other"


def report(data: Path, frame_us: float, top: int) -> list[str]:
    """The profile's lines: by place, then the top functions, in µs of a frame."""
    text = subprocess.run(
        [
            "perf",
            "report",
            "-i",
            str(data),
            "--no-children",
            "--sort",
            "dso,symbol",
            "--stdio",
            "-g",
            "none",
            "-t",
            "|",
        ],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    shares: dict[tuple[str, str], float] = defaultdict(float)
    for line in text.splitlines():
        fields = [field.strip() for field in line.split("|")]
        if len(fields) < 3 or not fields[0].endswith("%"):
            continue
        share, dso, symbol = (
            float(fields[0][:-1]),
            fields[1],
            fields[2].removeprefix("[.] ").removeprefix("[k] "),
        )
        library = "JIT" if dso.startswith("[JIT]") else dso.split(".cpython")[0]
        shares[(library, numba_symbol(symbol))] += share
    places: dict[str, float] = defaultdict(float)
    for (dso, symbol), share in shares.items():
        places[_where(dso, symbol)] += share
    lines = [
        f"{frame_us:.0f} µs a frame (a frame a call, under perf)",
        "",
        "| where | µs/frame | share |",
        "|---|---|---|",
    ]
    lines += [
        f"| {p} | {s / 100 * frame_us:.1f} | {s:.1f} % |"
        for p, s in sorted(places.items(), key=lambda i: -i[1])
    ]
    lines += ["", "| function | where | µs/frame | share |", "|---|---|---|---|"]
    ranked = sorted(shares.items(), key=lambda i: -i[1])[:top]
    lines += [
        f"| `{symbol[:70]}` | {dso} | {share / 100 * frame_us:.1f} | {share:.1f} % |"
        for (dso, symbol), share in ranked
    ]
    return lines


def profile(seconds: float, reflectors: int, n_frames: int, top: int) -> list[str]:
    """Run the stream under perf; the report's lines."""
    from echoloc.benchmark import bench_scene, pinned_cores
    from echoloc.pipeline import prepare
    from echoloc.realtime.stream import StreamProcessor, recording_frames
    from echoloc.sim.simulation import simulate
    from echoloc.tof.echoes import EchoOptions

    with pinned_cores(1):  # one core, as `echoloc bench` times the chain
        recording = simulate(bench_scene(reflectors), n_frames)
        chain = prepare(recording, echo_options=EchoOptions(workers=1))
        frames = list(recording_frames(recording))
        processor = StreamProcessor(chain)
        processor.warm_up()
        for frame in frames:
            processor.process(frame)  # every kernel compiled before the perf map is written
        mapped = write_perf_map()
        if not mapped:
            sys.exit("profile_stream: no compiled functions to map (were the kernels loaded from a cache?)")
        print(f"profile_stream: {mapped} compiled functions mapped", file=sys.stderr)
        with tempfile.TemporaryDirectory() as scratch:
            data = Path(scratch) / "perf.data"
            perf = subprocess.Popen(
                ["perf", "record", "-F", "2000", "-p", str(os.getpid()), "-o", str(data)],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
            time.sleep(1.0)  # perf attached
            done = 0
            started = time.perf_counter()
            while time.perf_counter() - started < seconds:
                for frame in frames:
                    processor.process(frame)
                done += len(frames)
            frame_us = (time.perf_counter() - started) / done * 1e6
            perf.send_signal(2)
            perf.wait(30)
            try:
                return report(data, frame_us, top)
            finally:
                perf_map_path().unlink(missing_ok=True)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=15.0, help="how long to sample (default 15)")
    parser.add_argument("--reflectors", type=int, default=5, help="random reflectors a frame (default 5)")
    parser.add_argument("--frames", type=int, default=200, help="frames simulated and replayed (default 200)")
    parser.add_argument("--top", type=int, default=25, help="functions listed (default 25)")
    parser.add_argument("--markdown", type=Path, default=None, help="also write the report here")
    args: Any = parser.parse_args(argv)
    if shutil.which("perf") is None:
        sys.exit("profile_stream: needs Linux perf (Debian: apt install linux-perf)")
    if "ECHOLOC_PROFILE_CACHE" not in os.environ:
        # Machine code loaded from the cache lists no functions: run again with an empty
        # cache of its own, so the kernels are compiled in the profiled process.
        cache = tempfile.mkdtemp(prefix="echoloc-profile-")
        env = {**os.environ, "NUMBA_CACHE_DIR": cache, "ECHOLOC_PROFILE_CACHE": cache}
        code = subprocess.run([sys.executable, *sys.argv], env=env).returncode
        shutil.rmtree(cache, ignore_errors=True)
        sys.exit(code)
    lines = profile(args.seconds, args.reflectors, args.frames, args.top)
    print("\n".join(lines))
    if args.markdown is not None:
        command = " ".join(["python benchmarks/profile_stream.py", *sys.argv[1:]])
        stamp = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
        header = ["# profile_stream.py — last run", "", f"`{command}` on {stamp}.", ""]
        args.markdown.write_text("\n".join([*header, *lines, ""]), encoding="utf-8")


if __name__ == "__main__":
    main()
