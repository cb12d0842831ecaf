"""The driver side: a job's config and its checks (`config`), where config groups' files are
found (`sources`), the objects, the grid of episodes, and the job service (`job.run_job`)."""
