"""Decoding ROS 2 messages read back from MCAP, for the tests of the exports."""

from __future__ import annotations

from typing import Any

import numpy as np


def cloud_points(msg: Any) -> np.ndarray:
    """A ``sensor_msgs/PointCloud2``'s points as a structured array, decoded from the message's
    own field list (names, offsets, FLOAT32), never from an assumed layout."""
    assert msg.is_bigendian is False
    assert all(f.datatype == 7 and f.count == 1 for f in msg.fields)  # FLOAT32
    dtype = np.dtype(
        {
            "names": [f.name for f in msg.fields],
            "formats": ["<f4"] * len(msg.fields),
            "offsets": [f.offset for f in msg.fields],
            "itemsize": msg.point_step,
        }
    )
    assert msg.height == 1
    assert msg.row_step == msg.point_step * msg.width
    assert len(msg.data) == msg.row_step * msg.height
    return np.frombuffer(bytes(msg.data), dtype=dtype)
