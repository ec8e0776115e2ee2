"""The statically stable crawl (Focchi et al. 2017, Section II) with the height reflex hooked in."""
