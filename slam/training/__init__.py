"""Training the weight networks end to end through the pose optimum (DDN)."""
