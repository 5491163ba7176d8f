"""File formats: Inria 3DGS PLY (:mod:`.ply`) and camera models (:mod:`.cameras`)."""
