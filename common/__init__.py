"""hoi-refine common package."""
