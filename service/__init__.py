"""Estimator service: REST jobs, live windows from Zenoh, Rerun logging."""
