"""hoi-refine migrations package."""
