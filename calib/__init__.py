"""Camera calibration: ChArUco intrinsics, camera response, vignetting (same anatomy as a stage)."""
