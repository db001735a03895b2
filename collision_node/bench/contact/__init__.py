"""Contact benchmarks under gravity: piles, stacks and resting contact.

``pile`` (the 2-D pile against pymunk, the 3-D pour against MuJoCo),
``stacks`` (columns, pyramids, drops, a falling cluster) and ``resting``
(what each preset pays to hold a pile still); each is a subcommand of
``python -m collision_node.bench``.
"""
