"""Maps: occupancy grids, submaps, map files and the map self-check."""
