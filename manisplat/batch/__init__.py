"""``manisplat-batch``: many episodes through validate -> reconstruct -> augment -> one dataset, as Ray
tasks (or one after another without Ray)."""
