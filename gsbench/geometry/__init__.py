"""Geometry helpers shared by methods: nearest neighbours (`neighbours`), neighbourhood covariance
(`local_geometry`), the batched symmetric 3x3 eigen-solver (`eigen3`), rotations (`rotations`) and the
3D smoothing filter of GOF / RaDe-GS (`filter3d`)."""
