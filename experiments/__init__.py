"""Scripts that regenerate every figure and table of hyqjax, one command each."""
