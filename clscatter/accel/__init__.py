"""Ray tracing acceleration: a binned-SAH BVH built on the host (NumPy), traversed in
OpenCL (``cl_kernels/bvh.h``). See :mod:`clscatter.accel.bvh`."""
