"""What the compiled kernels ([fast] extra) buy: the chain's time a frame, compiled and as plain Python.

Without numba the kernels run as the Python functions they are written as
(``echoloc._jit``; ``ECHOLOC_DISABLE_NUMBA=1`` forces it). Each round runs a worker
process per mode, one after the other, on the same recording; each worker times
``run(prepare(recording))`` over the frames, after one warm-up pass (numba's cache
loaded, numpy's first calls made), so imports and compilation are left out. The medians of
the rounds and their ratio are printed as a Markdown table.

    python benchmarks/bench_uncompiled.py [--frames 40] [--rounds 3]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

SCENES = {
    "report's three balls (rf)": "report-three-balls",
    "1-5 random reflectors (rf)": "random-1m3",
    "CH101-like head (envelope)": "ch101",
}

WORKER = """
import json, sys, time
from echoloc.io.recording import read_recording
from echoloc.pipeline import prepare, run
recording = read_recording(sys.argv[1])
list(run(prepare(recording, estimator="auto")))  # warm-up: caches loaded, first calls made
start = time.perf_counter()
results = list(run(prepare(recording, estimator="auto")))
elapsed = time.perf_counter() - start
print(json.dumps({"ms_per_frame": 1e3 * elapsed / recording.n_frames,
                  "objects": sum(len(objects.objects) for _, objects in results)}))
"""


def _worker(recording: Path, uncompiled: bool) -> dict[str, float]:
    env = dict(os.environ)
    env.pop("ECHOLOC_DISABLE_NUMBA", None)
    if uncompiled:
        env["ECHOLOC_DISABLE_NUMBA"] = "1"
    done = subprocess.run(
        [sys.executable, "-W", "ignore", "-c", WORKER, str(recording)],
        capture_output=True,
        text=True,
        env=env,
        check=True,
    )
    result: dict[str, float] = json.loads(done.stdout)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    from echoloc.io.recording import write_recording
    from echoloc.sim.scenefile import load_scene
    from echoloc.sim.simulation import simulate

    print(f"{args.frames} frames a scene, median of {args.rounds} rounds, ms a frame\n")
    print("| scene | compiled | plain Python | ratio | objects (both) |")
    print("|---|---:|---:|---:|---|")
    with tempfile.TemporaryDirectory() as folder:
        for label, preset in SCENES.items():
            recording = Path(folder) / f"{preset}.h5"
            write_recording(simulate(load_scene(preset), args.frames), recording)
            compiled, plain = [], []
            objects = set()
            for _ in range(args.rounds):
                for uncompiled, times in ((False, compiled), (True, plain)):
                    result = _worker(recording, uncompiled)
                    times.append(result["ms_per_frame"])
                    objects.add(int(result["objects"]))
            fast, slow = statistics.median(compiled), statistics.median(plain)
            same = "same" if len(objects) == 1 else f"differ: {sorted(objects)}"
            print(f"| {label} | {fast:.3f} | {slow:.2f} | {slow / fast:.0f}x | {same} |")


if __name__ == "__main__":
    main()
