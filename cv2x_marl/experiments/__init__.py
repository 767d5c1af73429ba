"""The paper's pipelines, driven by the CLI."""
