"""Helpers of the ``epipolar`` method (hierarchical volumetric shadows, Baran et al. 2010).

``geometry``  epipolar axis, slice placement (sinh distribution), (alpha, beta, gamma)
              coordinates, the host/device structs ``EPI_FRAME`` and ``EPI_SLICE``.
``svd``       the visibility-free part of the integrand and its truncated SVD.
``maps``      ray-traced shadow and camera depth maps (``cl_kernels/epipolar.cl``).
``pipeline``  rectification, Fenwick-tree integration and unrectification for one light.

The method class itself lives in :mod:`clscatter.methods.epipolar`.
"""
