"""Benchmarks: ``python -m scripts.benchmarks.bench`` (jaxnm beside Mitsuba 3 in one run),
the problem both renderers solve (`bench_problem`), Mitsuba's side (`bench_mitsuba`) and the
timer every script that times something uses (`timing`)."""
