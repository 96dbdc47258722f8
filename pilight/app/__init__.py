"""`pilight app` (the `app` extra): relight a photo in the browser, the light following the pointer.

lighting.py: the ball picker's geometry and the mixing of lights; session.py: one decomposed photo,
relit per light; ui.py: the Gradio page. Only ui.py imports Gradio.
"""
