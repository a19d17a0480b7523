"""hoi-refine service package."""
