"""Hostile inputs for echoloc: mutators, seeds and a watchdog that judges every run.

A case is one echoloc command on one hostile input (a mutated recording, scene or
calibration file). It passes when it ends in exit 0, or in exit 2 with a one-line
message, within :data:`HANG_S` and under :data:`MEMORY_LIMIT_BYTES`, with no traceback.
Everything else is a finding, kept with the input that caused it.

Mutators take a :class:`random.Random` so that a run is reproducible from its seed; the
test suite drives them from hypothesis (``tests/test_fuzz.py``), the long run from a
seeded loop (``fuzz/run.py``).
"""

from __future__ import annotations

import json
import math
import os
import random
import select
import shutil
import subprocess
import sys
import time
import tomllib
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import tomli_w

UNNAMED_WARNING = "[harness] a warning that names no input: "
HANG_S = 10.0
MEMORY_LIMIT_BYTES = 1 << 30
ROOT = Path(__file__).resolve().parents[1]
WORKER = Path(__file__).with_name("worker.py")

# ----------------------------------------------------------------------------- the judge


@dataclass(frozen=True)
class Outcome:
    """How one case ended."""

    exit: int | None  # None: killed (hang or memory)
    stderr: str
    seconds: float
    peak_rss_bytes: int
    hung: bool = False
    over_memory: bool = False

    @property
    def traceback(self) -> bool:
        return "Traceback (most recent call last)" in self.stderr

    @property
    def problems(self) -> list[str]:
        """What is wrong with this outcome (empty: a clean exit 0 or 2)."""
        found = []
        if self.hung:
            found.append("hang")
        if self.over_memory or self.peak_rss_bytes > MEMORY_LIMIT_BYTES:
            found.append("memory")
        if self.traceback:
            found.append("traceback")
        if self.exit not in (None, 0, 2):
            found.append(f"exit {self.exit}")
        if UNNAMED_WARNING in self.stderr:
            found.append("warning naming no file")
        if self.exit == 2 and not any(
            line.startswith("echoloc: error:") for line in self.stderr.splitlines()
        ):
            found.append("exit 2 without an error line")
        return found


def rss_bytes(pid: int) -> int:
    """The resident memory of process ``pid`` now (Linux /proc), bytes; 0 once it is gone."""
    try:
        with open(f"/proc/{pid}/status") as status:
            for line in status:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


class Worker:
    """A child process (``fuzz/worker.py``) running echoloc commands; replaced when a case
    hangs past ``hang_s`` or its resident memory passes ``memory_limit_bytes``."""

    def __init__(self, hang_s: float = HANG_S, memory_limit_bytes: int = MEMORY_LIMIT_BYTES) -> None:
        self.hang_s = hang_s
        self.memory_limit_bytes = memory_limit_bytes
        self.restarts = 0
        self.reruns = 0  # cases judged again alone in a fresh worker (their memory figure)
        self.hang_reruns = 0  # cases that passed hang_s, judged again alone (a loaded machine)
        self._process: subprocess.Popen[str] | None = None
        self._answers: Any = None

    def _start(self) -> None:
        read_fd, write_fd = os.pipe()
        env = {**os.environ, "PYTHONFAULTHANDLER": "0", "COLUMNS": "120"}
        self._process = subprocess.Popen(
            [sys.executable, str(WORKER), str(write_fd)],
            stdin=subprocess.PIPE,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,  # the command's stderr is captured in-process
            pass_fds=(write_fd,),
            text=True,
            env=env,
        )
        os.close(write_fd)
        self._answers = os.fdopen(read_fd, "r")
        line = self._wait_line(120.0)  # imports (numba, scipy) take a few seconds
        if line is None or not json.loads(line).get("ready"):
            raise RuntimeError("the fuzz worker did not start")

    def _rss_bytes(self) -> int:
        assert self._process is not None
        return rss_bytes(self._process.pid)

    def _wait_line(self, timeout_s: float) -> str | None:
        """The worker's next answer, or None when it took longer than ``timeout_s`` or died."""
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            ready, _, _ = select.select([self._answers], [], [], min(left, 0.05))
            if ready:
                line: str = self._answers.readline()
                return line or None
            if self._rss_bytes() > self.memory_limit_bytes:
                raise MemoryError
        return None

    def kill(self) -> None:
        if self._process is not None:
            self._process.kill()
            self._process.wait()
            if self._process.stdin is not None:
                self._process.stdin.close()
            self._answers.close()
            self._process = None

    def run(self, argv: list[str], cwd: Path, hang_s: float | None = None, alone: bool = False) -> Outcome:
        """Run ``echoloc ARGV`` in ``cwd`` and judge how it ended (``hang_s``: instead of the
        worker's bound, for warm-up runs that compile kernels; ``alone``: this is the rerun of
        a case in a fresh worker)."""
        if self._process is None:
            self._start()
        assert self._process is not None
        assert self._process.stdin is not None
        start = time.monotonic()
        try:
            self._process.stdin.write(json.dumps({"argv": argv, "cwd": str(cwd)}) + "\n")
            self._process.stdin.flush()
            line = self._wait_line(self.hang_s if hang_s is None else hang_s)
        except MemoryError:
            self.kill()
            self.restarts += 1
            if not alone:
                self.reruns += 1
                return self.run(argv, cwd, hang_s, alone=True)
            return Outcome(None, "", time.monotonic() - start, self.memory_limit_bytes + 1, over_memory=True)
        except BrokenPipeError:
            line = None
        if line is None:
            died = self._process.poll() is not None
            self.kill()
            self.restarts += 1
            if not died and not alone:
                # On a shared, loaded machine a slow case can pass the bound: a hang is a case
                # that passes it again, alone in a fresh worker.
                self.hang_reruns += 1
                return self.run(argv, cwd, hang_s, alone=True)
            return Outcome(None, "worker died" if died else "", time.monotonic() - start, 0, hung=not died)
        answer = json.loads(line)
        outcome = Outcome(answer["exit"], answer["stderr"], answer["seconds"], answer["peak_rss_bytes"])
        if outcome.peak_rss_bytes > self.memory_limit_bytes:
            self.kill()  # the peak sticks to a process: start afresh so the next case is judged alone
            self.restarts += 1
            if not alone:
                self.reruns += 1
                # The figure is an upper bound (the worker's own peak, grown over thousands of
                # cases, plus the HDF5 reader child's): the case is judged again in a fresh worker.
                return self.run(argv, cwd, hang_s, alone=True)
        return outcome

    def __enter__(self) -> Worker:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.kill()


@dataclass
class Tally:
    """Counts of cases by family and outcome, and the first inputs of every kind of finding."""

    cases: Counter[str] = field(default_factory=Counter)
    exits: Counter[tuple[str, str]] = field(default_factory=Counter)
    problems: Counter[tuple[str, str]] = field(default_factory=Counter)
    examples: dict[tuple[str, str], str] = field(default_factory=dict)
    notes: dict[str, int] = field(default_factory=dict)
    slowest_s: float = 0.0
    peak_rss_bytes: int = 0

    def add(self, family: str, outcome: Outcome, description: str) -> None:
        self.cases[family] += 1
        self.exits[family, "killed" if outcome.exit is None else str(outcome.exit)] += 1
        self.slowest_s = max(self.slowest_s, outcome.seconds)
        self.peak_rss_bytes = max(self.peak_rss_bytes, outcome.peak_rss_bytes)
        for problem in outcome.problems:
            self.problems[family, problem] += 1
            last_lines = " | ".join(outcome.stderr.strip().splitlines()[-2:])
            self.examples.setdefault((family, problem), f"{description}: {last_lines}"[:600])

    @property
    def clean(self) -> bool:
        return not self.problems


# ----------------------------------------------------------------------------- hostile values

# Numbers at the edges of every type a reader meets (the fuzz campaign's findings among them).
HOSTILE_NUMBERS: tuple[Any, ...] = (
    0,
    -1,
    1,
    0.5,
    -0.0,
    5e-324,
    -5e-324,
    1e-300,
    1e300,
    -1e300,
    math.inf,
    -math.inf,
    math.nan,
    2**31,
    2**31 - 1,
    2**53 + 1,
    2**63 - 1,
    -(2**63),
    1_000_000,
    1e9,
)
HOSTILE_OTHERS: tuple[Any, ...] = (True, False, "", "x" * 5000, "50000", "nan", [], [1.0, 2.0], {}, {"a": 1})


def hostile_value(rng: random.Random, like: Any = None) -> Any:
    """A value to put where ``like`` was: an edge number, a wrong type, a scaled or reshaped ``like``."""
    roll = rng.random()
    if like is not None and isinstance(like, int | float) and not isinstance(like, bool) and roll < 0.25:
        return like * rng.choice((-1, 0, 1e-9, 1e9, 10**12, 1.0000001))
    if like is not None and isinstance(like, list) and like and roll < 0.45:
        choice = rng.randrange(4)
        if choice == 0:
            return like[:-1] or []  # one element short
        if choice == 1:
            return [*like, like[-1]]  # one too many
        if choice == 2:
            return [hostile_value(rng, like[0]), *like[1:]]
        return [like]  # nested one level deeper
    if roll < 0.8:
        return rng.choice(HOSTILE_NUMBERS)
    return rng.choice(HOSTILE_OTHERS)


def _leaves(tree: Any, path: tuple[Any, ...] = ()) -> Iterator[tuple[tuple[Any, ...], Any]]:
    """Every (path, value) in a nested dict/list, the containers included."""
    yield path, tree
    if isinstance(tree, dict):
        for key, value in tree.items():
            yield from _leaves(value, (*path, key))
    elif isinstance(tree, list):
        for index, value in enumerate(tree):
            yield from _leaves(value, (*path, index))


def _set(tree: Any, path: tuple[Any, ...], value: Any) -> Any:
    if not path:
        return value
    node = tree
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    return tree


def _delete(tree: Any, path: tuple[Any, ...]) -> Any:
    node = tree
    for key in path[:-1]:
        node = node[key]
    del node[path[-1]]
    return tree


def mutate_tree(rng: random.Random, tree: Any, n_mutations: int = 1) -> tuple[Any, str]:
    """A copy of a parsed TOML/JSON document with one or a few hostile changes, and what they were."""
    tree = json.loads(json.dumps(tree))
    done = []
    for _ in range(n_mutations):
        paths = [path for path, _ in _leaves(tree) if path]
        if not paths:
            break
        path = rng.choice(paths)
        value = _leaves_get(tree, path)
        roll = rng.random()
        if roll < 0.12:
            tree = _delete(tree, path)
            done.append(f"del {_name(path)}")
        elif roll < 0.2 and isinstance(tree, dict):
            parent = path[:-1]
            node = _leaves_get(tree, parent)
            if isinstance(node, dict):
                node[f"unknown_{rng.randrange(100)}"] = hostile_value(rng)
                done.append(f"unknown key under {_name(parent) or 'top'}")
        else:
            new = hostile_value(rng, value)
            tree = _set(tree, path, new)
            done.append(f"{_name(path)} = {_short(new)}")
    return tree, "; ".join(done)


def _leaves_get(tree: Any, path: tuple[Any, ...]) -> Any:
    for key in path:
        tree = tree[key]
    return tree


def _name(path: tuple[Any, ...]) -> str:
    return ".".join(str(key) for key in path)


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) < 60 else text[:57] + "..."


def mutate_bytes(
    rng: random.Random, data: bytes, hot: list[tuple[int, int]] | None = None
) -> tuple[bytes, str]:
    """``data`` with one byte-level corruption: a flipped bit, overwritten bytes, an edge integer,
    a truncation, an insertion or a duplicated block. ``hot`` ranges (metadata) are hit more often."""
    buffer = bytearray(data)
    n = len(buffer)
    if n == 0:
        return bytes(rng.randbytes(rng.randrange(1, 64))), "random bytes"

    def position() -> int:
        if hot and rng.random() < 0.8:
            start, stop = rng.choice(hot)
            return rng.randrange(start, max(start + 1, min(stop, n)))
        return rng.randrange(n)

    kind = rng.randrange(7)
    at = min(position(), n - 1)
    if kind == 0:
        buffer[at] ^= 1 << rng.randrange(8)
        return bytes(buffer), f"bit flip at {at}"
    if kind == 1:
        width = rng.choice((1, 2, 4, 8))
        buffer[at : at + width] = bytes([rng.choice((0x00, 0xFF, 0x7F, 0x80))]) * width
        return bytes(buffer[:n]), f"{width} bytes set at {at}"
    if kind == 2:
        width = rng.choice((4, 8))
        value = rng.choice((2**31, 2**31 - 1, 2**32 - 1, 2**63 - 1, 2**64 - 1, 10_000_000, 1))
        buffer[at : at + width] = (value % (1 << (8 * width))).to_bytes(width, "little")
        return bytes(buffer[:n]), f"integer {value} at {at}"
    if kind == 3:
        cut = rng.randrange(n)
        return bytes(buffer[:cut]), f"truncated to {cut}"
    if kind == 4:
        junk = rng.randbytes(rng.randrange(1, 32))
        return bytes(buffer[:at] + junk + buffer[at:]), f"{len(junk)} bytes inserted at {at}"
    if kind == 5:
        width = rng.randrange(1, 32)
        buffer[at : at + width] = rng.randbytes(width)
        return bytes(buffer[:n]), f"{width} random bytes at {at}"
    source = rng.randrange(n)
    width = rng.randrange(1, 64)
    buffer[at : at + width] = data[source : source + width]
    return bytes(buffer[:n]), f"block from {source} copied to {at}"


# ----------------------------------------------------------------------------- seeds

TINY_SCENE = """\
# A small scene for the fuzz seeds: four receivers, two reflectors, short frames.
seed = 7

[array]
transmitters_m = [[0.0, 0.0, 0.0]]
receivers_m = [[0.1, 0.0, 0.0], [-0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [0.0, -0.1, 0.0]]

[pulse]
code = "barker7"
carrier_hz = 40e3
cycles_per_bit = 2

[acquisition]
sample_rate_hz = 160e3
n_samples = 600
frame_rate_hz = 100

[noise]
snr_db = 30

[[reflectors]]
position_m = [0.05, 0.02, 0.5]

[[reflectors]]
position_m = [-0.08, 0.03, 0.7]
"""


def scene_seeds() -> list[Path]:
    """Every scene preset shipped with echoloc."""
    paths = sorted((ROOT / "src" / "echoloc" / "scenes").rglob("*.toml"))
    return [path for path in paths if "sweep" not in path.name]


@dataclass(frozen=True)
class Seeds:
    """Valid inputs that the mutators start from, made once per run in ``folder``."""

    folder: Path
    recordings: tuple[Path, ...]
    calibration: Path
    calibrated_recording: Path
    scenes: tuple[Path, ...]


def make_seeds(worker: Worker, folder: Path) -> Seeds:
    """Simulate small recordings (HDF5 and NPZ, rf and envelope) and calibrate one, through the CLI."""
    folder.mkdir(parents=True, exist_ok=True)
    scene = folder / "tiny.toml"
    scene.write_text(TINY_SCENE)
    envelope_scene = folder / "tiny-envelope.toml"
    envelope_scene.write_text(
        TINY_SCENE.replace(
            "[noise]", '[receiver]\nsignal_kind = "envelope"\nrecord_waveform = false\n\n[noise]'
        )
    )
    made = []
    calibration = folder / "cal.json"
    commands = [
        ["simulate", str(scene), "-o", str(folder / "rf.h5"), "--frames", "3"],
        ["simulate", str(scene), "-o", str(folder / "rf.npz"), "--frames", "3"],
        ["simulate", str(envelope_scene), "-o", str(folder / "envelope.h5"), "--frames", "3"],
        ["calibrate", str(folder / "rf.h5"), "-o", str(calibration)],
    ]
    # The first runs compile the kernels (minutes on a cold cache): no hang bound for them.
    warm_up = [["locate", str(folder / name), "--json"] for name in ("rf.h5", "envelope.h5")]
    warm_up += [["echoes", str(folder / name), "--json"] for name in ("rf.h5", "envelope.h5")]
    warm_up.append(["locate", str(folder / "rf.h5"), "--calibration", str(calibration)])
    for argv in commands + warm_up:
        outcome = worker.run(argv, folder, hang_s=600.0)
        if outcome.exit != 0:
            raise RuntimeError(
                f"seed `echoloc {' '.join(argv)}`: exit {outcome.exit}, {outcome.stderr.strip()}"
            )
    made = [folder / name for name in ("rf.h5", "rf.npz", "envelope.h5")]
    return Seeds(folder, tuple(made), calibration, made[0], (*tuple(scene_seeds()), scene))


def hdf5_metadata_ranges(path: Path) -> list[tuple[int, int]]:
    """Byte ranges of ``path`` that are not raw sample data (the superblock, object headers,
    attributes, B-trees): where a corruption reaches the library's parsing."""
    size = path.stat().st_size
    data_ranges = []
    with h5py.File(path, "r") as f:
        for item in f.values():
            if isinstance(item, h5py.Dataset) and item.id.get_offset() is not None:
                data_ranges.append((item.id.get_offset(), item.id.get_offset() + item.id.get_storage_size()))
    data_ranges.sort()
    hot, cursor = [], 0
    for start, stop in data_ranges:
        if start > cursor:
            hot.append((cursor, start))
        cursor = max(cursor, stop)
    if cursor < size:
        hot.append((cursor, size))
    return hot or [(0, size)]


# ----------------------------------------------------------------------------- the families


def _read_items(path: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    if path.suffix == ".npz":
        with np.load(path, allow_pickle=False) as loaded:
            items = {name: loaded[name] for name in loaded.files}
        attrs = {k: v for k, v in items.items() if v.ndim == 0}
        return attrs, {k: v for k, v in items.items() if v.ndim != 0}
    with h5py.File(path, "r") as f:
        return dict(f.attrs), {name: f[name][()] for name in f if isinstance(f[name], h5py.Dataset)}


def _hostile_array(rng: random.Random, like: np.ndarray) -> np.ndarray | str:
    """A dataset to put where ``like`` was: wrong shape, dtype or values."""
    choice = rng.randrange(9)
    if choice == 0:
        return np.full_like(like, np.nan) if like.dtype.kind in "fc" else like[..., :0]
    if choice == 1:
        return like.reshape(-1)
    if choice == 2:
        return like[..., :1]
    if choice == 3:
        return like.astype(np.int8)
    if choice == 4:
        return np.asarray(["abc"] * max(like.size, 1), dtype="S3")
    if choice == 5:
        return np.asarray(rng.choice((0.0, 1e300, -1.0)))
    if choice == 6:
        return "huge"  # a declared-huge dataset with no data written
    if choice == 7:
        return np.concatenate([like, like], axis=0) if like.ndim else like
    return like.astype(np.complex64) if like.dtype.kind == "f" else like.astype(np.float16)


def mutate_recording(rng: random.Random, seed: Path, out_dir: Path) -> tuple[Path, str]:
    """A hostile recording made from ``seed``: a structural change (an attribute or dataset
    replaced, removed or added) or a byte-level corruption of the file."""
    suffix = seed.suffix
    target = out_dir / f"case{suffix}"
    target.unlink(missing_ok=True)
    if rng.random() < 0.45:
        hot = hdf5_metadata_ranges(seed) if suffix == ".h5" else None
        data, what = mutate_bytes(rng, seed.read_bytes(), hot)
        target.write_bytes(data)
        return target, f"{seed.name}: {what}"
    attrs, data = _read_items(seed)
    names = sorted(attrs) + sorted(data)
    name = rng.choice(names)
    roll = rng.random()
    huge = False
    if roll < 0.15:
        attrs.pop(name, None)
        data.pop(name, None)
        what = f"removed {name}"
    elif name in attrs:
        value = hostile_value(rng, attrs[name].item() if hasattr(attrs[name], "item") else attrs[name])
        if isinstance(value, dict) or value is None:
            value = str(value)
        if isinstance(value, int) and not isinstance(value, bool) and not -(2**63) <= value < 2**63:
            value = float(value)
        if isinstance(value, list) and any(isinstance(v, list | dict) for v in value):
            value = str(value)
        attrs[name] = value
        what = f"attribute {name} = {_short(value)}"
    else:
        new = _hostile_array(rng, np.asarray(data[name]))
        if isinstance(new, str):
            huge = True
            del data[name]
        else:
            data[name] = new
        what = f"dataset {name} -> {'declared 10^7 x 4 x 10^4, unwritten' if huge else _short(new)[:40]}"
    if suffix == ".npz":
        np.savez(target, **{k: np.asarray(v) for k, v in {**attrs, **data}.items()})
    else:
        with h5py.File(target, "w") as f:
            for key, value in attrs.items():
                f.attrs[key] = value
            for key, value in data.items():
                f.create_dataset(key, data=value)
            if huge:
                f.create_dataset(name, shape=(10_000_000, 4, 10_000), dtype="f4", chunks=(1, 4, 10_000))
    return target, f"{seed.name}: {what}"


def mutate_scene(rng: random.Random, seed: Path, out_dir: Path) -> tuple[Path, str]:
    """A hostile scene file: hostile values in a parsed seed, or a byte-level corruption of its text."""
    target = out_dir / "scene.toml"
    text = seed.read_text()
    roll = rng.random()
    if roll < 0.2:
        data, what = mutate_bytes(rng, text.encode())
        target.write_bytes(data)
        return target, f"{seed.name}: {what}"
    if roll < 0.25:
        depth = rng.choice((100, 3000, 100_000))
        target.write_text(text + f"\nnested = {'[' * depth}{']' * depth}\n")
        return target, f"{seed.name}: array nested {depth} deep"
    if roll < 0.3:
        target.write_text(text.replace("= ", "= 1" + "0" * 5000 + " #", 1))
        return target, f"{seed.name}: a 5000-digit number"
    tree, what = mutate_tree(rng, tomllib.loads(text), n_mutations=rng.choice((1, 1, 2)))
    try:
        target.write_text(tomli_w.dumps(_toml_ready(tree)))
    except (TypeError, ValueError) as error:  # a value TOML cannot hold: write it as text
        target.write_text(text + f"\n# {error}\n")
        what += " (unwritable, seed kept)"
    return target, f"{seed.name}: {what}"


def _toml_ready(tree: Any) -> Any:
    """TOML has no null and a top level must be a table."""
    if not isinstance(tree, dict):
        return {"value": tree}
    return tree


def mutate_calibration(rng: random.Random, seed: Path, out_dir: Path) -> tuple[Path, str]:
    """A hostile calibration file: hostile values in the seed's JSON, or broken JSON text."""
    target = out_dir / "cal.json"
    text = seed.read_text()
    roll = rng.random()
    if roll < 0.15:
        data, what = mutate_bytes(rng, text.encode())
        target.write_bytes(data)
        return target, f"{what}"
    if roll < 0.2:
        depth = rng.choice((3000, 100_000))
        target.write_text("[" * depth + "]" * depth)
        return target, f"nested {depth} deep"
    if roll < 0.25:
        target.write_text(text.replace(": ", ": 1" + "0" * 5000 + ', "_": ', 1))
        return target, "a 5000-digit number"
    tree, what = mutate_tree(rng, json.loads(text), n_mutations=rng.choice((1, 1, 2)))
    target.write_text(json.dumps(tree, allow_nan=True))
    return target, what


@dataclass(frozen=True)
class Family:
    """One kind of hostile input: how to make a case and which command reads it."""

    name: str
    make: Callable[[random.Random, Seeds, Path], tuple[list[str], str]]


def _recording_case(rng: random.Random, seeds: Seeds, folder: Path) -> tuple[list[str], str]:
    path, what = mutate_recording(rng, rng.choice(seeds.recordings), folder)
    command = rng.choice((["locate", "--json"], ["echoes", "--json"], ["locate"]))
    return [command[0], str(path), *command[1:]], what


def _scene_case(rng: random.Random, seeds: Seeds, folder: Path) -> tuple[list[str], str]:
    path, what = mutate_scene(rng, rng.choice(seeds.scenes), folder)
    return ["simulate", str(path), "-o", str(folder / "out.h5"), "--frames", "2"], what


def _calibration_case(rng: random.Random, seeds: Seeds, folder: Path) -> tuple[list[str], str]:
    path, what = mutate_calibration(rng, seeds.calibration, folder)
    return ["locate", str(seeds.calibrated_recording), "--calibration", str(path), "--json"], what


FAMILIES = {
    "recordings": Family("recordings", _recording_case),
    "scenes": Family("scenes", _scene_case),
    "calibrations": Family("calibrations", _calibration_case),
}


def run_family(
    worker: Worker, seeds: Seeds, family: Family, rng: random.Random, tally: Tally, folder: Path
) -> Outcome:
    """Make one case of ``family`` in ``folder``, run it and count it."""
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    argv, what = family.make(rng, seeds, folder)
    outcome = worker.run(argv, folder)
    inputs = [Path(arg).name for arg in argv if "/" in arg]
    unnamed = [
        line
        for line in outcome.stderr.splitlines()
        if line.startswith("echoloc: warning:") and not any(name in line for name in inputs)
    ]
    if unnamed:  # every warning about an input names it (the "warnings that name no file")
        outcome = replace(outcome, stderr=outcome.stderr + "\n" + UNNAMED_WARNING + unnamed[0])
    tally.add(family.name, outcome, f"echoloc {argv[0]} [{what}]")
    return outcome
