"""Studies of accuracy, each ``python -m scripts.studies.<name> --out DIR``: `study_frames`
(which tangent frame), `study_baking` (decoding a map in the frame it was baked in),
`speed_vs_error` (every configuration timed and measured), `hard_cases` (worst pixels and
finite gradients), `blender_bake_cases` (maps baked by Blender), `study_representations`
(normal, derivative, height and object-space maps stored, filtered and blended as engines
do)."""
