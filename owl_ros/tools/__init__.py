"""Tools around the product: evaluation (``evaluate``), benchmark (``bench``), soak
(``soak``), live latency (``latency``), demo (``demo``) and figures (``plots``), and
:class:`~owl_ros.tools.live.LiveNode`, the one way they and the tests run ``owl_node`` in
its own process. The product (``owl_ros.node``, ``pipeline``, ``params``, ``process``)
never imports this package."""
