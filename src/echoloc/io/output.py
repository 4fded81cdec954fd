"""Machine-readable output: the JSON Lines of docs/FORMATS.md for ``echoes`` and ``locate``."""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from echoloc.localise.locate import FrameObjects
from echoloc.localise.surfaces import Surface
from echoloc.tof.echoes import FrameEchoes


def echoes_record(echoes: FrameEchoes) -> dict[str, Any]:
    """One frame of ``echoloc echoes --json`` (docs/FORMATS.md)."""
    c = echoes.speed_of_sound_m_s
    return {
        "frame": echoes.frame,
        "time_s": float(echoes.time_s),
        "channels": [
            {
                "receiver": receiver,
                "echoes": [
                    {
                        "tof_s": float(tof),
                        "path_m": float(tof * c),
                        "amplitude": float(amplitude),
                        "snr_db": float(snr),
                    }
                    for tof, amplitude, snr in zip(ch.tof_s, ch.amplitude, ch.snr_db, strict=True)
                ],
            }
            for receiver, ch in enumerate(echoes.channels)
        ],
    }


def objects_record(objects: FrameObjects) -> dict[str, Any]:
    """One frame of ``echoloc locate --json`` (docs/FORMATS.md).

    ``receivers`` counts distinct receivers. Optional fields beyond the contract:
    ``channels``, the transmitter-receiver pairs whose echoes support the object
    (more than ``receivers`` when frames of several transmitters are combined), and
    ``shared_echoes``, how many of those echoes it shares with another object
    (echoes of two reflectors that merged).
    """
    return {
        "frame": objects.frame,
        "time_s": float(objects.time_s),
        "objects": [
            {
                "position_m": [float(v) for v in o.position_m],
                "std_m": [float(v) for v in o.std_m],
                "receivers": len(set(o.receivers)),
                "score": float(o.score),
                "channels": len(o.receivers),
                "shared_echoes": o.shared,
                **({} if o.surface is None else surface_fields(o.surface)),
            }
            for o in objects.objects
        ],
    }


def _angle_std_deg(covariance: NDArray[np.float64]) -> float:
    """Angular standard deviation of a unit vector from its (tangent) covariance, degrees."""
    return math.degrees(math.sqrt(max(float(np.trace(covariance)), 0.0)))


def surface_fields(surface: Surface) -> dict[str, Any]:
    """The optional class fields of a located object (docs/FORMATS.md 4): ``kind`` and
    ``kind_confidence`` always; a plane's ``normal``, ``normal_std_deg``, ``distance_m``,
    ``distance_std_m`` and ``extent_m``; a corner's ``edge_direction`` and ``edge_std_deg``."""
    record: dict[str, Any] = {"kind": surface.kind, "kind_confidence": float(surface.confidence)}
    if surface.normal is not None and surface.normal_covariance is not None:
        record["normal"] = [float(v) for v in surface.normal]
        record["normal_std_deg"] = _angle_std_deg(surface.normal_covariance)
    if surface.distance_m is not None:
        record["distance_m"] = float(surface.distance_m)
        record["distance_std_m"] = float(surface.distance_std_m or 0.0)
    if surface.extent_m is not None:
        record["extent_m"] = float(surface.extent_m)
    if surface.edge_direction is not None and surface.edge_covariance is not None:
        record["edge_direction"] = [float(v) for v in surface.edge_direction]
        record["edge_std_deg"] = _angle_std_deg(surface.edge_covariance)
    return record


def json_line(record: dict[str, Any]) -> str:
    """Compact JSON on one line; NaN is not valid JSON and is refused."""
    return json.dumps(record, separators=(", ", ": "), allow_nan=False)
