"""File formats: Inria 3DGS PLY (:mod:`.ply`) and camera files, one module per format
(:mod:`.inria_cameras`, :mod:`.colmap`, :mod:`.nerf`, :mod:`.llff`; any of them via :mod:`.cameras`)."""
