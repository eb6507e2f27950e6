"""File input and output: images, meta.csv, landmarks, results."""
