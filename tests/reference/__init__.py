"""Plain numpy/float64 twins of the Warp kernels, used only by the tests."""
