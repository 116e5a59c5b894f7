"""One-off studies behind RESULTS.md and the shipped model's lineage: not installed by ``pip install .``, never
imported by the product (``pvm_labeler``, ``optstereo``, the flows of ``pipelines``); run from a checkout with
``python -m pipelines.studies.<name>``. Their tests are ``tests/studies`` (``make test-studies``)."""
