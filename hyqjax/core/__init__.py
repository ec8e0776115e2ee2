"""HyQ itself: constants (:mod:`.robot`), rotations (:mod:`.spatial`), kinematics (:mod:`.kinematics`);
the MJX-free types shared by the simulation and the controllers (:mod:`.types`)."""
