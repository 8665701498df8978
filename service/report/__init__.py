"""Reading results: analysis (predictions, held-out scores, confusion), the paper's
figures (plots), xarray and ArviZ export."""
