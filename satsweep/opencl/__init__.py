"""The OpenCL layer: devices, contexts, program builds (the only place that opens contexts)."""
