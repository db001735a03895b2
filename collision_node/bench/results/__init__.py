"""Benchmark results: the JSON files the benchmarks write, and the page rendered from them.

:mod:`.files` writes a results file for any benchmark given ``--out FILE`` or
``--results-dir [DIR]`` (the dispatcher adds both) and reads it back;
:mod:`.page` is ``python -m collision_node.bench report``, which renders
docs/performance.md from docs/performance/*.json and its template.
"""
