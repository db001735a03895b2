"""Stages that move particles: gravity, drift, drag and spin."""
