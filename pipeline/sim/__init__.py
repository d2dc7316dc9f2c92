"""The closed loop: the world (the lander's true dynamics and the sensors sampling it as it is
flown), the flight software (the navigator and guidance, which read only what the sensors give)
and the loop that runs them at their rates.

Pure like the core (numpy, scipy and `pipeline.core`; the import contract checks it): the `fly`
stage (`pipeline.ops.fly`) builds the objects from the config and turns the flight into tables.
"""
