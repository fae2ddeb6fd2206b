"""Learning from the robot's own driving, without middleware (issue 33, docs/calibration.md): velocity-tracking
outcomes, the experience store that pairs them with earlier predictions, calibration figures, the anchor
fitter, and the questions to an operator."""
