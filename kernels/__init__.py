"""Device code of warpcontact (`@wp.func` / `@wp.kernel`), installed as ``warpcontact.kernels``.

Modules by stage: ``linalg`` (small dense solves), ``geometry`` (closest features),
``leaf`` (separating-plane leaf potential, and the SDRS baseline's log-barrier variant),
``blend`` (centred potential, quintic blend).
"""
