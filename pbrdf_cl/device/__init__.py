"""The compute device: OpenCL drivers and kernel sources, the probe and choice of device, trial
builds, the OpenCL and numpy engines, the per-point transfers, the fallbacks, and the operations
with one implementation per backend.  The rest of the package takes the engines and what goes with
them from :mod:`pbrdf_cl.device.engine`, the layer's face."""
