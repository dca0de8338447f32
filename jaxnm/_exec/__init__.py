"""How jaxnm runs on XLA: the execution layer under the pipeline's stages.

The stages (`jaxnm.raster`, `jaxnm.interpolate`, `jaxnm.frames`, `jaxnm.textures`,
`jaxnm.shading`, `jaxnm.render`) say what a frame computes; the modules here decide how
XLA runs it, and never change a result. Each module's docstring says what it is for;
docs/guides/design.md gives the measurements behind each choice, with their commands.

- `fusion`: `materialize`, a fusion barrier that XLA's CPU backend keeps.
- `arrays`: small array operations in the forms XLA runs well (`cumsum`, `div`,
  `roll_last`, `xyw`).
- `compaction`: the true entries of a mask as indices (`flat_nonzero`, `ranked_nonzero`).
- `sums`: fixed-order sparse sums (`SumTables`).

Nothing here imports a stage: the stages call in, never the reverse.
"""
