"""The particle filter's math, plain numpy (DESIGN.md "The particle filter").

- ``weights`` (alias ``lw``): log-sum-exp, normalisation, ESS, NaN flags
- ``resampling`` (alias ``rs``): systematic / stratified / multinomial in the log domain, by name
- ``motion``: ParticleState, MotionParams, the decaying-velocity transition, initialisers
- ``likelihood_ref``: the numpy reference of the observation model (the GL shader's specification)
- ``estimate``: weighted mean pose and spread
- ``status``: ok / uncertain / lost rules
- ``particle_filter``: the per-frame stepper against an ObservationModel (``observation``)
"""
