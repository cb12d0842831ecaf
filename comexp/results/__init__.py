"""The results: the database (`store`), the tables and job reports (`reports`, with the one
grouping rule `group_episodes`), the figures (`plots`), the paper's numbers (`paper`) and the
notebook API (`api`: `comexp.load_results`, `comexp.replay`)."""
