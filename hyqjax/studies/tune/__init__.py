"""Tuning of the height reflex and the crawl for the step-down (see docs/tuning.md)."""
