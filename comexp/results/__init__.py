"""The results: the database (`store`, `schema`, `migrations`), an episode's identity
(`identity`), the tables and job reports (`reports`, with the one grouping rule
`group_episodes`), the figures (`plots`), the paper's claims and numbers (`claims`, `paper`)."""
