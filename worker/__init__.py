"""hoi-refine worker package."""
