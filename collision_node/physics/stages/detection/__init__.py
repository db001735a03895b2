"""Stages that find contacts: the broadphase grid and the narrowphase, with their kernels."""
