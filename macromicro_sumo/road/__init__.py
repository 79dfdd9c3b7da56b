"""Road geometry: the ring, sections of any network, lanes, leaders, pure physics."""
