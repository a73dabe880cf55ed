"""The Snakemake workflow, driven through its command line."""
