"""The documentation site's build helpers: `notebooks` (the tutorials executed once, for the
site) and `griffe_markdown` (the docstrings' reStructuredText leftovers as Markdown for the
API reference). `hooks` is mkdocs' entry point (``hooks:`` in ``mkdocs.yml``)."""
