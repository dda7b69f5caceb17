"""Orchestration layer: jobs that chain stages (dataset builds, the demo's steps).

Unlike the rest of :mod:`polspike`, modules here may import every stage
(generator, spike_sim, reconstruct), like the CLI; library stages never import
this package.
"""
