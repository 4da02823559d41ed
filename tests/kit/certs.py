"""Test certificates made with openssl: a CA, a server certificate for 127.0.0.1 and a client
certificate (MQTT and Sparkplug TLS tests)."""
import subprocess

from kit.tools import require_tool


def make_certs(d):
    """A CA, a server certificate for 127.0.0.1 and a client certificate (openssl)."""
    ossl = require_tool("openssl")

    def run(*a):
        subprocess.run([ossl, *a], check=True, capture_output=True, cwd=d, timeout=60)

    run("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca.key", "-out", "ca.crt", "-days", "2",
        "-subj", "/CN=hookwatch test CA")
    for name, ext in (("server", "subjectAltName=IP:127.0.0.1"), ("client", "extendedKeyUsage=clientAuth")):
        run("req", "-newkey", "rsa:2048", "-nodes", "-keyout", f"{name}.key", "-out", f"{name}.csr",
            "-subj", f"/CN={name}")
        (d / f"{name}.ext").write_text(ext + "\n")
        run("x509", "-req", "-in", f"{name}.csr", "-CA", "ca.crt", "-CAkey", "ca.key", "-CAcreateserial",
            "-out", f"{name}.crt", "-days", "2", "-extfile", f"{name}.ext")
    return {k: str(d / f"{k}") for k in ("ca.crt", "server.crt", "server.key", "client.crt", "client.key")}
