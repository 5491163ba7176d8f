"""The fuzz library of the test suite and ``scripts/fuzz.py`` (not shipped: users never import it).

* :mod:`tests.fuzzlib.gsc`: mutations of ``.gsc`` streams and the decode/info targets;
* :mod:`tests.fuzzlib.models`: seeds of every model format (SPZ v1-v4, .splat, SOG bundle and
  folder, compressed.ply, gsplat checkpoint, dynamic model directory), their truncations, byte
  edits and structured hostile values, read in-process or through the CLI;
* :mod:`tests.fuzzlib.zipfile_raw`: a zip writer that writes any lie (names, methods, sizes, CRCs).
"""
