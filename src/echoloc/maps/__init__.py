"""Occupancy maps: located objects accumulated into grids, and the grids exported."""
