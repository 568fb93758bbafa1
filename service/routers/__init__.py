"""REST routers: jobs, live rigs, health and metrics."""
