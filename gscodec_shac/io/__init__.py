"""File formats, one module per format. Models: Inria 3DGS PLY (:mod:`.ply`), SPZ (:mod:`.spz`),
.splat (:mod:`.splat`), SOG (:mod:`.sog`), compressed.ply (:mod:`.compressed_ply`), gsplat
checkpoints (:mod:`.gsplat_ckpt`); any of them via :mod:`.models`. Cameras: :mod:`.inria_cameras`,
:mod:`.colmap`, :mod:`.nerf`, :mod:`.llff`; any of them via :mod:`.cameras`."""
