"""The scheduler owns the curriculum: a reconcile step that is a pure function of database
state (``plan.plan``, over a ``snapshot.Snapshot``; ``reconcile`` applies it), the windowed stopping rule (``stopping``), and a service loop."""
