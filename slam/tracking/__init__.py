"""Tracking a sequence frame by frame: the tracker and its strategies (reference, acceptance,
graph), the cross-check, the health figures, loop closure on a pose graph, place recognition."""
