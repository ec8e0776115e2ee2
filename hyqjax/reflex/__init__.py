"""The height reflex (Focchi et al. 2017, Section III): parameters, geometry, forces, the reflex step."""
