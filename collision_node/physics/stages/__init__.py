"""Stages of a step, one per module; ``physics.plan.build_pipeline`` assembles them."""
