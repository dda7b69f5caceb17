"""polspike.pipeline: jobs that chain stages: manifests, sampler, dataset build/verify/inspect, trade-off bench, training windows.

Part of the application floor: may import every stage (generator, spike_sim,
reconstruct), like the CLI; no stage imports this package.
"""
