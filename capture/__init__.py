"""Capture agents: frame sources, segmentation and silhouette streaming over Zenoh."""
