"""On-demand benchmarks: run time against error, side by side with a baseline or peer.

Run ``python -m benchmarks list`` for what exists and ``python -m benchmarks NAME`` to run one.
Each benchmark is a module ``benchmarks/bench_<name>.py`` with a ``run(ctx)`` function.
"""
