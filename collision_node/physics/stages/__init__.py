"""Stages of a step, grouped by what they do, each beside its kernels.

``physics.step.plan.build_pipeline`` assembles them.
"""
