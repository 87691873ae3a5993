"""UI layer: the sidebar panels and the add-on preferences. Only addon/__init__.py and api.py sit above."""
