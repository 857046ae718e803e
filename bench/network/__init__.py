"""The network: shaped-link clusters, the trace-driven model and its report."""
