// Firmware in the loop: the cell's RP2040 firmware (its ELF, as built for a Pico) runs in
// rp2040js, Wokwi's RP2040 emulator, with UART0 on a Unix socket for mcu_bridge and every
// output pin change recorded with its emulated time.
//
//   node harness.mjs --elf FILE --socket PATH [--speed K] [--edges FILE] [--pins 0-15]
//                   [--profile FILE]
//
// * No boot ROM (the npm package ships none, and the firmware makes no ROM calls): the
//   ELF's loadable segments go to flash and SRAM by their load address, and the core starts
//   at the firmware's vector table (after the 256-byte boot2, which only sets up the flash
//   the emulator maps directly).
// * Paced: emulated time never runs ahead of wall time × speed, so the bridge's clock sync
//   sees a crystal, not a race. How far it falls behind is reported.
// * Bytes from the socket enter UART0's receive FIFO at the line's rate (921,600 baud, 8N1:
//   10.85 µs of emulated time per byte), never overfilling its 32 places, as a real line
//   would deliver them.
//
// First line of stdout: `socket PATH` once listening. On SIGTERM/SIGINT: one JSON line of
// figures (instructions, emulated and wall seconds, edges, the firmware's own counters read
// from its RAM by symbol).

import fs from 'node:fs';
import net from 'node:net';
import { Simulator } from 'rp2040js';

function parseArgs(argv) {
  const args = { speed: 1, pins: '0-15', vectorTable: 0x10000100 };
  for (let i = 0; i < argv.length; i += 2) {
    const key = argv[i].replace(/^--/, '').replace(/-([a-z])/g, (_, c) => c.toUpperCase());
    args[key] = argv[i + 1];
  }
  if (!args.elf || !args.socket) {
    console.error('usage: node harness.mjs --elf FILE --socket PATH [--speed K] [--edges FILE] [--pins 0-15]');
    process.exit(64);
  }
  args.speed = Number(args.speed);
  args.vectorTable = Number(args.vectorTable);
  const [lo, hi] = args.pins.split('-').map(Number);
  args.pinList = Array.from({ length: (hi ?? lo) - lo + 1 }, (_, k) => lo + k);
  return args;
}

/** Loadable segments and the symbol table of a 32-bit little-endian ELF. */
function readElf(bytes) {
  const b = Buffer.from(bytes);
  if (b.readUInt32BE(0) !== 0x7f454c46 || b[4] !== 1 || b[5] !== 1) {
    throw new Error('not a 32-bit little-endian ELF');
  }
  const phoff = b.readUInt32LE(0x1c), phentsize = b.readUInt16LE(0x2a), phnum = b.readUInt16LE(0x2c);
  const segments = [];
  for (let i = 0; i < phnum; i++) {
    const o = phoff + i * phentsize;
    if (b.readUInt32LE(o) !== 1) continue; // PT_LOAD
    const offset = b.readUInt32LE(o + 4), paddr = b.readUInt32LE(o + 12), filesz = b.readUInt32LE(o + 16);
    if (filesz > 0) segments.push({ paddr, data: b.subarray(offset, offset + filesz) });
  }
  const shoff = b.readUInt32LE(0x20), shentsize = b.readUInt16LE(0x2e), shnum = b.readUInt16LE(0x30);
  const sections = Array.from({ length: shnum }, (_, i) => {
    const o = shoff + i * shentsize;
    return { type: b.readUInt32LE(o + 4), offset: b.readUInt32LE(o + 16), size: b.readUInt32LE(o + 20), link: b.readUInt32LE(o + 24) };
  });
  const symbols = new Map();
  const functions = [];
  for (const s of sections.filter((s) => s.type === 2)) { // SHT_SYMTAB
    const strtab = sections[s.link];
    for (let o = s.offset; o < s.offset + s.size; o += 16) {
      const nameOff = b.readUInt32LE(o);
      const end = b.indexOf(0, strtab.offset + nameOff);
      const name = b.toString('latin1', strtab.offset + nameOff, end);
      const value = b.readUInt32LE(o + 4), size = b.readUInt32LE(o + 8);
      symbols.set(name, value);
      if ((b[o + 12] & 0xf) === 2 && size > 0) functions.push({ name, start: value & ~1, end: (value & ~1) + size });
    }
  }
  functions.sort((x, y) => x.start - y.start);
  return { segments, symbols, functions };
}

const args = parseArgs(process.argv.slice(2));
const elf = readElf(fs.readFileSync(args.elf));
const sim = new Simulator();
const mcu = sim.rp2040;
const clock = sim.clock;
for (const { paddr, data } of elf.segments) {
  if (paddr >= 0x10000000 && paddr < 0x11000000) mcu.flash.set(data, paddr - 0x10000000);
  else if (paddr >= 0x20000000 && paddr < 0x20042000) mcu.sram.set(data, paddr - 0x20000000);
  else throw new Error(`segment at 0x${paddr.toString(16)} is neither flash nor SRAM`);
}
const table = args.vectorTable - 0x10000000;
const flashView = new DataView(mcu.flash.buffer);
mcu.core.VTOR = args.vectorTable;
mcu.core.SP = flashView.getUint32(table, true);
mcu.core.PC = flashView.getUint32(table + 4, true) & ~1;

// Pin edges, buffered.
const edgesOut = args.edges ? fs.openSync(args.edges, 'w') : null;
let edgeLines = [];
let edgeCount = 0;
function flushEdges() {
  if (edgesOut !== null && edgeLines.length) fs.writeSync(edgesOut, edgeLines.join(''));
  edgeLines = [];
}
for (const pin of args.pinList) {
  mcu.gpio[pin].addListener((state, old) => {
    const level = state === 1 ? 1 : state === 0 ? 0 : null;
    const was = old === 1 ? 1 : old === 0 ? 0 : null;
    if (level === null || level === was) return;
    edgeCount++;
    if (edgesOut !== null) {
      edgeLines.push(`${Math.round(clock.nanos)},${pin},${level}\n`);
      if (edgeLines.length >= 8192) flushEdges();
    }
  });
}

// UART0 <-> the socket.
const BYTE_NS = 1e9 * 10 / 921600;
let client = null;
let pending = [];
let nextByteNs = 0;
let bytesIn = 0, bytesOut = 0;
mcu.uart[0].onByte = (byte) => {
  bytesOut++;
  if (client !== null) client.write(Buffer.from([byte]));
};
try { fs.unlinkSync(args.socket); } catch {}
const server = net.createServer((socket) => {
  if (client !== null) client.destroy();
  client = socket;
  socket.on('data', (chunk) => { for (const byte of chunk) pending.push(byte); });
  socket.on('close', () => { if (client === socket) client = null; });
  socket.on('error', () => {});
});
server.listen(args.socket, () => console.log(`socket ${args.socket}`));

// Optional profile: the program counter every 64th instruction, summed per function.
const profile = args.profile ? new Map() : null;
function writeProfile() {
  const perFunction = new Map();
  let total = 0;
  for (const [pc, n] of profile) {
    let lo = 0, hi = elf.functions.length - 1, found = null;
    while (lo <= hi) {
      const mid = (lo + hi) >> 1, f = elf.functions[mid];
      if (pc < f.start) hi = mid - 1; else if (pc >= f.end) lo = mid + 1; else { found = f.name; break; }
    }
    const name = found ?? `0x${pc.toString(16)}`;
    perFunction.set(name, (perFunction.get(name) ?? 0) + n);
    total += n;
  }
  const rows = [...perFunction].sort((a, b) => b[1] - a[1]).slice(0, 40)
    .map(([name, n]) => `${(100 * n / total).toFixed(2).padStart(6)} %  ${name}`);
  fs.writeFileSync(args.profile, rows.join('\n') + '\n');
}

// Paced execution.
const CYCLE_NS = 1e9 / 125e6;
const wallStart = process.hrtime.bigint();
let instructions = 0;
let maxLagNs = 0;
let pendingAt = 0;
function run() {
  const wallNs = Number(process.hrtime.bigint() - wallStart);
  const targetNs = wallNs * args.speed;
  maxLagNs = Math.max(maxLagNs, targetNs - clock.nanos);
  const budgetEnd = performance.now() + 20; // keep the event loop (socket I/O) responsive
  while (clock.nanos < targetNs && performance.now() < budgetEnd) {
    for (let i = 0; i < 2000 && clock.nanos < targetNs; i++) {
      if (pendingAt < pending.length && clock.nanos >= nextByteNs && !mcu.uart[0].rxFIFO.full) {
        mcu.uart[0].feedByte(pending[pendingAt++]);
        bytesIn++;
        nextByteNs = clock.nanos + BYTE_NS;
      }
      if (mcu.core.waiting) {
        // Asleep (WFI): on to the next timer alarm, the next byte, or the pacing target.
        let until = targetNs;
        if (pendingAt < pending.length) until = Math.min(until, Math.max(nextByteNs, clock.nanos + CYCLE_NS));
        clock.tick(Math.max(CYCLE_NS, Math.min(clock.nanosToNextAlarm, until - clock.nanos)));
      } else {
        if (profile !== null && (instructions & 63) === 0) profile.set(mcu.core.PC, (profile.get(mcu.core.PC) ?? 0) + 1);
        clock.tick(mcu.core.executeInstruction() * CYCLE_NS);
        instructions++;
      }
    }
  }
  if (pendingAt > 65536) { pending = pending.slice(pendingAt); pendingAt = 0; }
  setImmediate(run);
}

function readWord(name) {
  const address = elf.symbols.get(name);
  if (address === undefined || address < 0x20000000) return null;
  return new DataView(mcu.sram.buffer).getUint32(address - 0x20000000, true);
}

function finish() {
  flushEdges();
  if (profile !== null) writeProfile();
  const wallS = Number(process.hrtime.bigint() - wallStart) * 1e-9;
  const emulatedS = clock.nanos * 1e-9;
  console.log(JSON.stringify({
    instructions,
    emulated_s: emulatedS,
    wall_s: wallS,
    emulated_per_wall: emulatedS / wallS,
    instructions_per_wall_s: instructions / wallS,
    max_lag_ms: maxLagNs * 1e-6,
    pin_edges: edgeCount,
    uart_bytes_in: bytesIn,
    uart_bytes_out: bytesOut,
    isr_max_cycles: readWord('ISR_MAX_CYCLES'),
    main_max_cycles: readWord('MAIN_MAX_CYCLES'),
    edges_output: readWord('EDGES_OUTPUT'),
    rx_overruns: readWord('RX_OVERRUNS'),
    late_outputs: readWord('LATE_OUTPUTS'),
    pc: mcu.core.PC,
  }));
  process.exit(0);
}
process.on('SIGTERM', finish);
process.on('SIGINT', finish);
run();
