"""From echoes to positions: association across receivers and ellipsoid intersection,
back-projection, calibration, evaluation against the truth, position uncertainty."""
