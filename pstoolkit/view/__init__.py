"""``pstoolkit view``: a local relighting viewer for result folders and captures.

``source`` reads what is shown (a result folder's maps, or a capture's stored result or ground
truth), ``timeline`` scrubs a capture's frames, events and lights over time, ``server`` serves the
page (``static/``: HTML, JavaScript and CSS shipped with the package, no network at run time) and
the data, ``display`` is the page's shading and display encoding in Python (for tests), and
``sample`` writes a synthetic result folder to try it on.

    from pstoolkit.view.server import ViewServer
    from pstoolkit.view.source import load_result_folder

    server = ViewServer(load_result_folder(Path("out/demo-dualres"))).start()
    print(server.url)   # … server.close()
"""
