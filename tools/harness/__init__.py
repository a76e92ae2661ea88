"""The harness: runs rt_core against the references (mitsuba_ref) and measures it —
``validate`` (every scene against Mitsuba), ``compare`` (one scene), ``stability`` (generated
stiff cases against the exact oracle), ``report`` (error against run time) and ``bench``
(throughput and its timing helpers)."""
