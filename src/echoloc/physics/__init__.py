"""The physics the rest stands on: air (speed of sound, absorption), transducers (beams,
responses), the transmitted waveforms and codes, and the Cramér-Rao bounds on timing."""
