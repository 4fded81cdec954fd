"""Machine-readable output: the JSON Lines of docs/FORMATS.md for ``echoes`` and ``locate``."""

from __future__ import annotations

import json
from typing import Any

from echoloc.localise.locate import FrameObjects
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
            }
            for o in objects.objects
        ],
    }


def json_line(record: dict[str, Any]) -> str:
    """Compact JSON on one line; NaN is not valid JSON and is refused."""
    return json.dumps(record, separators=(", ", ": "), allow_nan=False)
