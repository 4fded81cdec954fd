"""Writing recording files by hand, without validation, so tests can break them on purpose."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import h5py
import numpy as np


def write_raw(path: Path, attrs: dict[str, Any], data: dict[str, Any]) -> Path:
    """Write attributes and datasets as given (HDF5, or NPZ for a .npz path), without any validation."""
    if path.suffix == ".npz":
        items: dict[str, Any] = {k: np.asarray(v) for k, v in {**attrs, **data}.items()}
        np.savez(path, **items)
    else:
        with h5py.File(path, "w") as f:
            for name, value in attrs.items():
                f.attrs[name] = value
            for name, value in data.items():
                f.create_dataset(name, data=value)
    return path
