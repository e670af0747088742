"""LinkGlide's servo bus: the interface, the Feetech driver, the simulators."""

KINDS = {
    "recording": "operator_side.servos.recording:RecordingServoBus",
    "feetech": "operator_side.servos.feetech:FeetechServoBus",
    "simulated_feetech": "operator_side.servos.sts_sim:SimulatedFeetechServoBus",
}
