"""The swept (ccd) stage: impacts at their time of impact inside the step, with its kernels."""
