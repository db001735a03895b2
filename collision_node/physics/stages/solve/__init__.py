"""Stages that solve contacts: sequential and batched impulses and walls, with their kernels."""
