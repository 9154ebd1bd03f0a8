"""The twin's objects: the paper's objects and user meshes (:mod:`.model`), their procedural shapes
(:mod:`.shapes`), geometry helpers (:mod:`.geometry`), textures and materials (:mod:`.textures`),
preview figures (:mod:`.plot`) and the ChArUco calibration board's texture (:mod:`.board`)."""
