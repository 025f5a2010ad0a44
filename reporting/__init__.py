"""The report's sections, one module per subject of the page (the capture, the fit, the scene and contact,
training, image quality, reenactment and the viewer, the comparison), and the page's building blocks. The report
stage assembles them; nothing else imports them but the tests."""
