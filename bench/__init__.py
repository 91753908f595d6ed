"""TeMoto benchmarks: ``python -m bench [--quick] [--json FILE]``.

See ``bench/README.md`` for what each metric measures and the latest results.
"""
