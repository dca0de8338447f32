"""Examples: ``python -m scripts.examples.make_example_scene`` (the torus scene in
``scripts/examples/scenes/torus/``), ``python -m scripts.examples.make_example_fit OUTDIR``
(the built-in fit problem as files for ``jaxnm fit``) and ``python -m scripts.examples.teaser``
(the picture at the top of the README and the documentation)."""
