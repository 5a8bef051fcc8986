"""Forward models fitted to (scene, measurement) pairs (``psfkit fit-pairs``, ``eval-model``)."""
