#!/usr/bin/env python3
"""Soak of `cadence serve`: N API clients subscribe to the status objects (updates every
250 ms) and query them at 4 Hz while the printer prints the first LINES lines of a G-code file
from its virtual sdcard; prints the service's `latency` object (lead margin in MCU-time ms,
hand-off and planner wake-up in µs) and each client's query/notification counts as JSON.

    scripts/serve-soak/soak.py --clients 8 --lines 30000 --time-scale 10

The printer is the reference benchy printer (shared data) on the simulated MCU, without
endstops (G28 homes without motion), in a scratch directory (--dir).
"""
import argparse, json, os, signal, socket, subprocess, threading, time

ap = argparse.ArgumentParser()
ap.add_argument('--clients', type=int, default=0)
ap.add_argument('--lines', type=int, default=30000)
ap.add_argument('--time-scale', default='10')
root = os.path.abspath(os.path.join(os.path.dirname(__file__), '..', '..'))
ap.add_argument('--exe', default=os.path.join(root, 'target/debug/cadence'))
ap.add_argument('--gcode', default=os.path.join(root, '../shared/data/gcode/benchy-prusaslicer.gcode'))
ap.add_argument('--printer', default=os.path.join(root, '../shared/data/printers/benchy-cartesian.cfg'))
ap.add_argument('--dir', default='/tmp/cadence-serve-soak')
a = ap.parse_args()

os.makedirs(os.path.join(a.dir, 'gcodes'), exist_ok=True)
cfg = [l for l in open(a.printer).read().replace('serial: /dev/ttyACM0', 'serial: simulator').splitlines()
       if not l.startswith(('endstop_pin', 'position_endstop', 'homing_speed'))]
open(os.path.join(a.dir, 'printer.cfg'), 'w').write('\n'.join(cfg) + '\n')
lines = open(a.gcode).read().splitlines()[:a.lines]
open(os.path.join(a.dir, 'gcodes', 'soak.gcode'), 'w').write('\n'.join(lines) + '\n')
sock = os.path.join(a.dir, 'api.sock')
if os.path.exists(sock):
    os.remove(sock)
srv = subprocess.Popen([a.exe, 'serve', '--config', os.path.join(a.dir, 'printer.cfg'), '--time-scale', a.time_scale,
                        '-a', sock, '--virtual-sdcard', os.path.join(a.dir, 'gcodes'), '--log-level', 'warn'],
                       stderr=open(os.path.join(a.dir, 'serve-%d.err' % a.clients), 'w'))


class Client:
    def __init__(self):
        self.s = socket.socket(socket.AF_UNIX)
        self.s.connect(sock)
        self.buf, self.n, self.notes = b'', 0, 0

    def read(self):
        while b'\x03' not in self.buf:
            d = self.s.recv(1 << 16)
            if not d:
                raise EOFError('the service closed the connection')
            self.buf += d
        m, _, self.buf = self.buf.partition(b'\x03')
        return json.loads(m)

    def call(self, method, params=None):
        self.n += 1
        self.s.sendall(json.dumps({'id': self.n, 'method': method, 'params': params or {}}).encode() + b'\x03')
        while True:
            r = self.read()
            if r.get('id') == self.n:
                return r
            self.notes += 1


for _ in range(600):
    try:
        main = Client()
        break
    except OSError:
        time.sleep(0.1)
while main.call('info')['result']['state'] != 'ready':
    time.sleep(0.2)
OBJS = {k: None for k in ['toolhead', 'gcode_move', 'print_stats', 'virtual_sdcard', 'display_status', 'idle_timeout',
                         'motion_report', 'system_stats', 'webhooks', 'mcu', 'latency', 'pause_resume']}
stop, stats = False, []


def client():
    c = Client()
    c.call('objects/subscribe', {'objects': OBJS, 'response_template': {}})
    queries = 0
    while not stop:
        c.call('objects/query', {'objects': OBJS})
        queries += 1
        time.sleep(0.25)
    stats.append((queries, c.notes))


threads = [threading.Thread(target=client) for _ in range(a.clients)]
for t in threads:
    t.start()
t0 = time.time()
r = main.call('gcode/script', {'script': 'G28\nSDCARD_PRINT_FILE FILENAME=soak.gcode'})
assert 'error' not in r, r
while True:
    st = main.call('objects/query', {'objects': {'print_stats': ['state', 'message'], 'webhooks': ['state']}})
    st = st['result']['status']
    if st['print_stats']['state'] != 'printing':
        break
    time.sleep(1)
wall = time.time() - t0
stop = True
for t in threads:
    t.join()
lat = main.call('objects/query', {'objects': {'latency': None}})['result']['status']['latency']
print(json.dumps({'clients': a.clients, 'lines': a.lines, 'time_scale': a.time_scale, 'wall_s': round(wall, 1),
                  'print': st, 'client_queries_notifications': stats, 'latency': lat}, indent=1))
srv.send_signal(signal.SIGTERM)
print('cadence serve exit', srv.wait())
