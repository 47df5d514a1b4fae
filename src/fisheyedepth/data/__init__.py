"""Data: the synthetic fisheye world, dataset readers and the DataModule."""
