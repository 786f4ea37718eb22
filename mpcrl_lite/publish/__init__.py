"""The notebooks as reports and as a site: papermill runs, offline HTML, figure texts.

- :mod:`~mpcrl_lite.publish.report`: notebooks as parameterised reports;
- :mod:`~mpcrl_lite.publish.html_export`: offline HTML pages;
- :mod:`~mpcrl_lite.publish.alt_text`: text alternatives of the figures;
- :mod:`~mpcrl_lite.publish.site`: the static site;
- :mod:`~mpcrl_lite.publish.launch`: Colab and Binder links, the install cell.

May import: :mod:`mpcrl_lite.classroom` and below.
"""
