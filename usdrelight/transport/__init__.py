"""The light-transport layer below the fit and the relight engine: what a stage's camera sees and how light
reaches it, independent of any light.

* :mod:`.surface` — the visible surface: one primary ray per pixel (hit points, shading and geometric normals
  facing the camera, albedo), the geometry-only Mitsuba scene for shadow rays, and each pixel's area-averaged
  albedo and coverage (what a box pixel filter sees);
* :mod:`.sampling` — stratified samples, cosine-weighted directions, Mitsuba ray batches, latlong cells;
* :mod:`.basis` — the environment visibility basis, the one-bounce gather on the visible 2.5D surface and its
  joint-bilateral filter, and shadow-tested point-light columns;
* :mod:`.cache` — the prepared transport of a stage under one content key, in one cache folder shared safely
  by sessions and processes (bounded size, eviction by age, never deleting a file another session holds).

The fit (:mod:`usdrelight.fit`) is this layer plus a target image; the engine (:mod:`usdrelight.engine`) is
this layer plus lights. Units: metres (the records' units), radiance in the stage's linear RGB.
"""
