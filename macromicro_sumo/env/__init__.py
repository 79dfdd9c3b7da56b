"""Stage II environments: the SUMO core and the gymnasium / PettingZoo wrappers."""
