"""Point-cloud stage (pipeline steps 4-5): feature mapping onto the visual hull and the point net."""
