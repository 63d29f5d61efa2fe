"""Device code of hlbvh_warp: ``@wp.kernel``, ``@wp.func`` and ``@wp.struct`` only.

One module per pipeline stage, so that editing one stage recompiles one module. Nothing here
allocates memory or launches kernels; the host side in ``hlbvh_warp`` does both.
"""
