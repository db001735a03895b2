"""The event-driven stage of the exact preset, with its event and resting kernels."""
