"""Baseline mappers the paper compares MSK-GPOM against: occupancy grid, GPOM, GPOMIK."""
