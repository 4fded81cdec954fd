"""Pictures (matplotlib): a frame, the physics (beams, spectra), images, maps, design studies."""
