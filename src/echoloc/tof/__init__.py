"""Time of flight: from a frame of received samples to echoes (arrival times, amplitudes,
uncertainty) through matched filters, envelopes, thresholds and fits; channel conditioning
and health; templates."""
