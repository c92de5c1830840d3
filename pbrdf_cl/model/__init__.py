"""The model: the float64 reference mirror of kernels/pbrdf.h and the registry of output quantities."""
