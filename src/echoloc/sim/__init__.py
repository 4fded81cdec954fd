"""The simulator: scenes and scene files, reflectors, the receiver chain, echo synthesis,
and ``simulate``, which turns a scene into a recording."""
