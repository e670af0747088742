"""LinkGlide's servo bus: the interface, the Feetech driver, the simulators."""

KINDS = {
    "in_memory": "operator_side.servos.in_memory:InMemoryServoBus",
    "feetech": "operator_side.servos.feetech:FeetechServoBus",
    "simulated_feetech": "operator_side.servos.sts_sim:SimulatedFeetechServoBus",
}
