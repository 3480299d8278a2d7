"""Whole sessions built from the nodes: `msk live`, the demo, the graph a deployment declares, and their scoring."""
