"""The step: the pipeline framework, its plan, the world, and the compiled-kernel set-up."""
