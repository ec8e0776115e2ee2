"""HyQ itself: constants (:mod:`.robot`), rotations (:mod:`.spatial`), kinematics (:mod:`.kinematics`)."""
