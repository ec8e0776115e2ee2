"""Results on disk and on screen: atomic files, traces, rendering, HTML reports."""
