"""Inversion: one data set (the staged pipeline), image stacks pixel by pixel, and their stores."""
