"""The Ray runtime on the driver: the coordinator, shard pools, placement, the call protocol."""
