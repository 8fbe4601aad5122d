"""The paper's experiments as runnable pipelines: thin scripts chaining datagen and gns."""
