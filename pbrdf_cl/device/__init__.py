"""The compute device: OpenCL drivers, the probe and choice of device, trial builds, the engines."""
