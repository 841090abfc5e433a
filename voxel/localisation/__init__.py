"""Localisation of one agent: odometry model, pose filter, scan matching, visual odometry,
trajectory metrics."""
