"""The separation stage: overlap removed without adding energy, with its kernels."""
