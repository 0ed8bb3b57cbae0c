"""Multi-view geometry on numpy and OpenCV (no torch): sparse points triangulated from posed RGB
(:mod:`mapper.geometry.triangulation`) and their settings (:mod:`mapper.geometry.config`)."""
