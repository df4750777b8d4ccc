"""Dense correspondence backends: temporal optical flow and stereo parallax flow."""
