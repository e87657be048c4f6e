"""Terrain geo-referencing (paper 1, sections 3 and 4.3): DEM, shading, phase correlation."""
