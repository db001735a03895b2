"""Stages of a step, one per module; ``pipeline.build_pipeline`` assembles them."""
