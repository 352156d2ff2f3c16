"""Readers and writers: point-cloud files, layouts, datasets, bags, Rerun, pictures, bag pairing."""
