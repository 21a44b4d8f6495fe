"""The scheduler owns the curriculum: a reconcile step that is a pure function of database
state (``reconcile.plan``), the windowed stopping rule (``stopping``), and a service loop."""
