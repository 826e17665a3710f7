"""Speed benchmarks of heartcv (run with ``python -m benchmarks all``; see ``benchmarks/README.md``).

Every benchmark reports the median of repeated ``time.perf_counter`` measurements and a ratio against a
baseline measured in the same run, so that the numbers can be compared across machines.
"""
