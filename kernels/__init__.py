"""Device code of warpcontact (`@wp.func` / `@wp.kernel`), installed as ``warpcontact.kernels``.

Modules by stage: ``rigid`` (poses to rotations, rigid-coordinate projections),
``traversal`` (sphere-tree pair lists), ``geometry`` (closest features, separating axes),
``linalg`` (small dense solves), ``leaf`` (separating-plane leaf potential, and the SDRS
baseline's log-barrier variant), ``blend`` (centred potential, quintic blend),
``reduction`` (term kernels, blend reduction, advancement bounds), ``friction`` (lagged
smoothed Coulomb damping and its adjoint), ``dynamics`` (inertia, gravity and PD terms of
the implicit step, their adjoints), ``state`` (taped start velocities) and ``task`` (task
losses and control parameterisations). docs/architecture.md maps them to the pipeline.
"""
