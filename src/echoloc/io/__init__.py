"""Files in and out: HDF5/NPZ recordings, importers of other data sets, JSON Lines, and
MCAP/PLY exports."""
