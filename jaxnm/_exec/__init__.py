"""How jaxnm runs on XLA: the execution layer under the pipeline's stages.

The stages (`jaxnm.raster`, `jaxnm.interpolate`, `jaxnm.frames`, `jaxnm.textures`,
`jaxnm.shading`, `jaxnm.gbuffer`, `jaxnm.render`) say what a frame computes; the modules
here decide how XLA runs it, and never change a result. A stage calls them by what they
do:

- `pixels`: evaluate a per-pixel function over the covered pixels (`over_covered_pixels`:
  packed, in passes and chunks), and whether a frame runs that way (`packs`).
- `slots`: the rasterizer's work as (triangle, tile) slots, taken a round at a time
  (`slot_list`, `slot_owners`, `over_rounds`), in passes (`each_pass`); `RasterStrategy`.
- `triangles`: each triangle's orientation and the tiles its box touches
  (`triangle_setup`), the corners as the slots read them (`Corners`).
- `depth`: the depth test's buffer, stored tile by tile (`empty_buffer`, `write`,
  `winners`).
- `compaction`: a mask's true entries as indices (`flat_nonzero`, `ranked_nonzero`).
- `sums`: fixed-order sparse sums (`SumTables`).
- `fusion`, `arrays`: a fusion barrier XLA keeps (`materialize`); small array operations in
  the forms XLA runs well (`cumsum`, `div`, `xyw`).

Each module's docstring says why; docs/guides/design.md gives the measurements behind each
choice, with their commands. Nothing here imports a stage: the stages call in, never the
reverse.
"""
