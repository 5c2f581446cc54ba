// Firmware in the loop: the cell's RP2040 firmware (its ELF, as built for a Pico) runs in
// rp2040js, Wokwi's RP2040 emulator, with UART0 on a Unix socket for mcu_bridge and every
// output pin change recorded with its emulated time.
//
//   node harness.mjs --elf FILE [--uf2 FILE] --socket PATH [--speed K] [--edges FILE]
//                   [--pins 0-15] [--profile FILE] [--uart-log FILE] [--corrupt-every N]
//                   [--link uart|usb] [--usb-lines FILE] [--switch-at S] [--stop-at S]
//
// * No boot ROM (the npm package ships none, and the firmware makes no ROM calls): the
//   ELF's loadable segments go to flash and SRAM by their load address — or, with --uf2, the
//   flash gets the UF2 file's blocks, as the boot ROM would write them — and the core starts
//   at the firmware's vector table (after the 256-byte boot2, which only sets up the flash
//   the emulator maps directly).
// * Paced: emulated time never runs ahead of wall time × speed, so the bridge's clock sync
//   sees a crystal, not a race. How far it falls behind is reported.
// * Bytes from the socket enter UART0's receive FIFO at the line's rate (921,600 baud, 8N1:
//   10.85 µs of emulated time per byte), never overfilling its 32 places, as a real line
//   would deliver them.
//
// * --uart-log: every byte entering UART0 with its emulated time (`time_ns,byte` lines), for
//   a checker to find when a frame (an emergency stop, say) reached the MCU.
// * --corrupt-every N: a damaged line — every Nth byte to the MCU has a bit flipped (never
//   into a frame delimiter), so frames fail their CRC and the link must resend them.
//
// * USB (with --link usb or --usb-lines; else no host is plugged in): a host on the
//   emulated USB controller enumerates the firmware's composite device
//   and opens both CDC-ACM ports (DTR set). --link usb puts the socket on the first port (the
//   wire protocol over USB) instead of UART0; --usb-lines records the second port's lines
//   (`time_ns,line`).
// * --switch-at S: the start switch (GP15, pulled up) is held to ground for 100 ms from
//   emulated second S. --stop-at S: stop (and report) at emulated second S.
// * --replay-uart FILE (instead of --socket): feed UART0 the bytes of an earlier run's
//   --uart-log at their recorded emulated times, so that two builds of the firmware can be
//   measured on exactly the same input (run it with a large --speed and --stop-at).
//
// First line of stdout: `socket PATH` once listening. On SIGTERM/SIGINT: one JSON line of
// figures (instructions, emulated and wall seconds, edges, the core's load — the share of
// cycles it executed rather than slept in WFI/WFE, over the run and over its busiest 100 ms —
// and the firmware's own counters read from its RAM by symbol).

import fs from 'node:fs';
import net from 'node:net';
import {
  ConsoleLogger, LogLevel, Simulator, createSetupPacket, getDescriptorPacket, setDeviceAddressPacket,
  setDeviceConfigurationPacket,
} from 'rp2040js';

function parseArgs(argv) {
  const args = { speed: 1, pins: '0-15', vectorTable: 0x10000100 };
  for (let i = 0; i < argv.length; i += 2) {
    const key = argv[i].replace(/^--/, '').replace(/-([a-z])/g, (_, c) => c.toUpperCase());
    args[key] = argv[i + 1];
  }
  if (!args.elf || (!args.socket && !args.replayUart)) {
    console.error('usage: node harness.mjs --elf FILE --socket PATH [--speed K] [--edges FILE] [--pins 0-15]');
    process.exit(64);
  }
  args.speed = Number(args.speed);
  args.corruptEvery = Number(args.corruptEvery ?? 0);
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

/** The flash image a UF2 file writes, as the RP2040's boot ROM would: 512-byte blocks with
 *  their magic numbers, the RP2040's family ID and a target address in flash. */
function readUf2(bytes) {
  const b = Buffer.from(bytes);
  if (b.length === 0 || b.length % 512 !== 0) throw new Error(`UF2: ${b.length} bytes is not a whole number of 512-byte blocks`);
  const blocks = [];
  for (let o = 0; o < b.length; o += 512) {
    const n = o / 512;
    if (b.readUInt32LE(o) !== 0x0a324655 || b.readUInt32LE(o + 4) !== 0x9e5d5157 || b.readUInt32LE(o + 508) !== 0x0ab16f30) {
      throw new Error(`UF2 block ${n}: bad magic`);
    }
    const flags = b.readUInt32LE(o + 8), target = b.readUInt32LE(o + 12), size = b.readUInt32LE(o + 16);
    const blockNo = b.readUInt32LE(o + 20), count = b.readUInt32LE(o + 24), family = b.readUInt32LE(o + 28);
    if ((flags & 0x2000) === 0 || family !== 0xe48bff56) throw new Error(`UF2 block ${n}: not for the RP2040 (family 0x${family.toString(16)})`);
    if (blockNo !== n || count !== b.length / 512) throw new Error(`UF2 block ${n}: numbered ${blockNo} of ${count}`);
    if (size > 476 || target < 0x10000000 || target + size > 0x10200000) throw new Error(`UF2 block ${n}: ${size} bytes at 0x${target.toString(16)} are not in the Pico's flash`);
    blocks.push({ paddr: target, data: b.subarray(o + 32, o + 32 + size) });
  }
  return blocks;
}

const args = parseArgs(process.argv.slice(2));
const elf = readElf(fs.readFileSync(args.elf));
const sim = new Simulator();
const mcu = sim.rp2040;
const clock = sim.clock;
// rp2040js logs every USB transfer and unimplemented register (the ring oscillator's random
// bit, read 32 times for the link's nonce) at info/warn level: errors only.
mcu.logger = new ConsoleLogger(LogLevel.Error);
// The firmware feeds the RP2040's watchdog each pass of its main loop; rp2040js only logs a
// trigger (no reset), so a loop that stalled past it would pass unnoticed: fail the run.
mcu.peripherals[0x40058].onWatchdogTrigger = () => {
  console.error('harness: the watchdog triggered: the firmware\'s main loop stalled past it');
  process.exit(3);
};
// With --uf2 the flash is what a Pico would be flashed with (the ELF only names the counters).
const image = args.uf2 ? readUf2(fs.readFileSync(args.uf2)) : elf.segments;
for (const { paddr, data } of image) {
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
let bytesIn = 0, bytesOut = 0, bytesCorrupted = 0;
let usbEarly = []; // link bytes that came before the USB ports were open
let usbBytesIn = 0, usbBytesOut = 0, usbLines = 0;
const uartLog = args.uartLog ? fs.openSync(args.uartLog, 'w') : null;
let uartLines = [];
function flushUartLog() {
  if (uartLog !== null && uartLines.length) fs.writeSync(uartLog, uartLines.join(''));
  uartLines = [];
}
mcu.uart[0].onByte = (byte) => {
  bytesOut++;
  if (client !== null) client.write(Buffer.from([byte]));
};
// A recorded input instead of a live host: [emulated ns, byte] in order.
const replay = args.replayUart
  ? fs.readFileSync(args.replayUart, 'utf8').split('\n').filter((l) => l.length > 0)
    .map((l) => l.split(',').map(Number))
  : [];
let replayAt = 0;
if (args.socket) try { fs.unlinkSync(args.socket); } catch {}
const server = net.createServer((socket) => {
  if (client !== null) client.destroy();
  client = socket;
  socket.on('data', (chunk) => {
    if (args.link === 'usb') {
      if (usbPorts.length > 0) { usbPorts[0].toDevice.push(...chunk); usbFeed(usbPorts[0]); }
      else usbEarly.push(...chunk);
    } else {
      for (const byte of chunk) pending.push(byte);
    }
  });
  socket.on('close', () => { if (client === socket) client = null; });
  socket.on('error', () => {});
});
if (args.socket) server.listen(args.socket, () => console.log(`socket ${args.socket}`));


// USB host: enumerate the firmware's composite device and open its CDC-ACM ports.
const CDC_SET_CONTROL_LINE_STATE = 0x22;
const usb = mcu.usbCtrl;
const usbPorts = []; // in CDC order: { comm, in, out, toDevice: [], onData }
const usbStepAlarm = clock.createAlarm(() => usbNext());
let usbState = 'off';
let usbDescriptorsSize = 0;
let usbDescriptors = [];
let usbLineStateFor = 0;
let usbConfigured = false;
/** The next step of enumeration, a millisecond on: the firmware polls USB every 250 µs. */
function usbLater() { usbStepAlarm.schedule(1e6); }
function usbNext() {
  switch (usbState) {
    case 'address':
      usbState = 'config9';
      usb.sendSetupPacket(getDescriptorPacket(2, 9));
      break;
    case 'config9':
      usbState = 'config';
      usbDescriptors = [];
      usb.sendSetupPacket(getDescriptorPacket(2, usbDescriptorsSize));
      break;
    case 'config':
      parseCdcPorts(usbDescriptors);
      usbState = 'configure';
      usb.sendSetupPacket(setDeviceConfigurationPacket(1));
      break;
    case 'configure':
    case 'lineState':
      if (usbLineStateFor < usbPorts.length) {
        usbState = 'lineState';
        // DTR | RTS on the port's communication interface (class request to the interface).
        usb.sendSetupPacket(createSetupPacket({
          dataDirection: 0, type: 1, recipient: 1, bRequest: CDC_SET_CONTROL_LINE_STATE,
          wValue: 3, wIndex: usbPorts[usbLineStateFor++].comm, wLength: 0,
        }));
      } else {
        usbState = 'ready';
        usbConfigured = true;
        for (const port of usbPorts) usbFeed(port);
      }
      break;
  }
}
/** The CDC data interfaces in order, each with its bulk endpoints and the communication
 *  interface before it. */
function parseCdcPorts(d) {
  let comm = -1, current = null;
  for (let i = 0; i + 1 < d.length && d[i] >= 2; i += d[i]) {
    const [len, type] = [d[i], d[i + 1]];
    if (type === 4 && len >= 9) { // interface
      current = null;
      if (d[i + 5] === 2) comm = d[i + 2];
      if (d[i + 5] === 10) { current = { comm, in: -1, out: -1, toDevice: [], onData: null }; usbPorts.push(current); }
    } else if (type === 5 && len >= 7 && current !== null && (d[i + 3] & 3) === 2) { // bulk endpoint
      if (d[i + 2] & 0x80) current.in = d[i + 2] & 0xf; else current.out = d[i + 2] & 0xf;
    }
  }
  if (usbPorts.length !== 2) throw new Error(`USB: ${usbPorts.length} CDC ports, expected 2`);
  // The first port: the wire protocol (with --link usb, the socket's).
  const link = usbPorts[0];
  link.toDevice.push(...usbEarly);
  usbEarly = [];
  link.onData = (buffer) => {
    usbBytesOut += buffer.length;
    if (args.link === 'usb' && client !== null) client.write(Buffer.from(buffer));
  };
  link.onDelivered = (chunk) => {
    usbBytesIn += chunk.length;
    if (uartLog !== null) for (const byte of chunk) uartLines.push(`${Math.round(clock.nanos)},${byte}\n`);
  };
  // The second: position lines.
  const linesOut = args.usbLines ? fs.openSync(args.usbLines, 'w') : null;
  let partial = '';
  usbPorts[1].onData = (buffer) => {
    partial += Buffer.from(buffer).toString('latin1');
    let end;
    while ((end = partial.indexOf('\n')) >= 0) {
      const line = partial.slice(0, end).replace(/\r$/, '');
      partial = partial.slice(end + 1);
      usbLines++;
      if (linesOut !== null) fs.writeSync(linesOut, `${Math.round(clock.nanos)},${line}\n`);
    }
  };
}
/** The status stage of a request that read data: a zero-length OUT, once the data is in
 *  and the device has armed endpoint 0 for it (an earlier one would end the request early). */
let usbStatusDue = false, usbEp0Armed = false;
function usbStatusOut() {
  if (!usbStatusDue || !usbEp0Armed) return;
  usbStatusDue = usbEp0Armed = false;
  usb.endpointReadDone(0, new Uint8Array(0));
}
/** Hand the device what waits for it, if it has a buffer armed. */
const usbArmed = new Map(); // OUT endpoint -> bytes the device's armed buffer takes
function usbFeed(port) {
  const armed = usbArmed.get(port.out) ?? 0;
  if (!usbConfigured || armed === 0 || port.toDevice.length === 0) return;
  const chunk = Uint8Array.from(port.toDevice.splice(0, armed));
  usbArmed.set(port.out, 0);
  usb.endpointReadDone(port.out, chunk);
  if (port.onDelivered) port.onDelivered(chunk);
}
// Plugged in only when a test uses USB: otherwise the Pico is powered without a USB host
// (the protocol on UART0, as a rig with a UART adapter), and the firmware's USB stays idle.
const usbWanted = args.link === 'usb' || args.usbLines !== undefined;
usb.onUSBEnabled = () => { if (usbWanted) usb.resetDevice(); };
usb.onResetReceived = () => { usbState = 'address'; usb.sendSetupPacket(setDeviceAddressPacket(1)); };
usb.onEndpointWrite = (endpoint, buffer) => {
  if (endpoint === 0) {
    if (usbState === 'config9' && buffer.length >= 4) usbDescriptorsSize = buffer[2] | (buffer[3] << 8);
    if (usbState === 'config') usbDescriptors.push(...buffer);
    // Status (no data) ends a request; data ends with a short packet or the length asked.
    const dataDone = usbState === 'config9' ||
      (usbState === 'config' && usbDescriptors.length >= usbDescriptorsSize);
    if (dataDone) { usbStatusDue = true; usbStatusOut(); }
    if (dataDone || buffer.length === 0) usbLater();
    return;
  }
  const port = usbPorts.find((p) => p.in === endpoint);
  if (port && port.onData) port.onData(buffer);
};
usb.onEndpointRead = (endpoint, size) => {
  if (endpoint === 0) { usbEp0Armed = true; usbStatusOut(); return; }
  // Armed perhaps before enumeration names the port: remembered by endpoint.
  usbArmed.set(endpoint, size);
  const port = usbPorts.find((p) => p.out === endpoint);
  if (port) usbFeed(port);
};

// The start switch (GP15, to ground; the pull-up holds it high) and the end of the run.
mcu.gpio[15].setInputValue(true);
if (args.switchAt !== undefined) {
  const release = clock.createAlarm(() => mcu.gpio[15].setInputValue(true));
  clock.createAlarm(() => { mcu.gpio[15].setInputValue(false); release.schedule(100e6); })
    .schedule(Number(args.switchAt) * 1e9);
}
let stopNow = false;
if (args.stopAt !== undefined) clock.createAlarm(() => { stopNow = true; }).schedule(Number(args.stopAt) * 1e9);

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
  // Every sampled address too, for a per-line view (`llvm-addr2line -i -e ELF`).
  const pcs = [...profile].sort((a, b) => b[1] - a[1])
    .map(([pc, n]) => `0x${pc.toString(16)} ${n}`);
  fs.writeFileSync(`${args.profile}.pcs`, pcs.join('\n') + '\n');
}

// Paced execution.
const CYCLE_NS = 1e9 / 125e6;
const wallStart = process.hrtime.bigint();
let instructions = 0;
// Load: cycles the core executed (not asleep in WFI), in all and over the busiest 100 ms.
const LOAD_WINDOW_NS = 100e6;
let busyCycles = 0, windowBusyCycles = 0, windowStartNs = 0, peakLoad = 0;
let maxLagNs = 0;
let pendingAt = 0;
function run() {
  const wallNs = Number(process.hrtime.bigint() - wallStart);
  const targetNs = wallNs * args.speed;
  maxLagNs = Math.max(maxLagNs, targetNs - clock.nanos);
  const budgetEnd = performance.now() + 20; // keep the event loop (socket I/O) responsive
  while (clock.nanos < targetNs && performance.now() < budgetEnd && !stopNow) {
    for (let i = 0; i < 2000 && clock.nanos < targetNs; i++) {
      if (pendingAt < pending.length && clock.nanos >= nextByteNs && !mcu.uart[0].rxFIFO.full) {
        let byte = pending[pendingAt++];
        if (args.corruptEvery > 0 && (bytesIn + 1) % args.corruptEvery === 0) {
          byte ^= byte === 0x10 ? 0x20 : 0x10;
          bytesCorrupted++;
        }
        mcu.uart[0].feedByte(byte);
        if (uartLog !== null) {
          uartLines.push(`${Math.round(clock.nanos)},${byte}\n`);
          if (uartLines.length >= 8192) flushUartLog();
        }
        bytesIn++;
        nextByteNs = clock.nanos + BYTE_NS;
      }
      if (replayAt < replay.length && clock.nanos >= replay[replayAt][0] && !mcu.uart[0].rxFIFO.full) {
        mcu.uart[0].feedByte(replay[replayAt++][1]);
        bytesIn++;
      }
      if (mcu.core.waiting) {
        // Asleep (WFI): on to the next timer alarm, the next byte, or the pacing target.
        let until = targetNs;
        if (replayAt < replay.length) until = Math.min(until, Math.max(replay[replayAt][0], clock.nanos + CYCLE_NS));
        if (pendingAt < pending.length) until = Math.min(until, Math.max(nextByteNs, clock.nanos + CYCLE_NS));
        clock.tick(Math.max(CYCLE_NS, Math.min(clock.nanosToNextAlarm, until - clock.nanos)));
      } else {
        if (profile !== null && (instructions & 63) === 0) profile.set(mcu.core.PC, (profile.get(mcu.core.PC) ?? 0) + 1);
        const cycles = mcu.core.executeInstruction();
        clock.tick(cycles * CYCLE_NS);
        instructions++;
        busyCycles += cycles;
        windowBusyCycles += cycles;
      }
      if (clock.nanos - windowStartNs >= LOAD_WINDOW_NS) {
        peakLoad = Math.max(peakLoad, windowBusyCycles * CYCLE_NS / (clock.nanos - windowStartNs));
        windowStartNs = clock.nanos;
        windowBusyCycles = 0;
      }
    }
  }
  if (pendingAt > 65536) { pending = pending.slice(pendingAt); pendingAt = 0; }
  if (stopNow) { finish(); return; }
  setImmediate(run);
}

function readWord(name) {
  const address = elf.symbols.get(name);
  if (address === undefined || address < 0x20000000) return null;
  return new DataView(mcu.sram.buffer).getUint32(address - 0x20000000, true);
}

function finish() {
  flushEdges();
  flushUartLog();
  if (profile !== null) writeProfile();
  const wallS = Number(process.hrtime.bigint() - wallStart) * 1e-9;
  const emulatedS = clock.nanos * 1e-9;
  console.log(JSON.stringify({
    instructions,
    emulated_s: emulatedS,
    wall_s: wallS,
    emulated_per_wall: emulatedS / wallS,
    instructions_per_wall_s: instructions / wallS,
    cpu_load: busyCycles * CYCLE_NS / clock.nanos,
    cpu_load_peak_100ms: peakLoad,
    max_lag_ms: maxLagNs * 1e-6,
    pin_edges: edgeCount,
    uart_bytes_in: bytesIn,
    uart_bytes_out: bytesOut,
    uart_bytes_corrupted: bytesCorrupted,
    isr_max_cycles: readWord('ISR_MAX_CYCLES'),
    main_max_cycles: readWord('MAIN_MAX_CYCLES'),
    edges_output: readWord('EDGES_OUTPUT'),
    rx_overruns: readWord('RX_OVERRUNS'),
    late_step_outputs: readWord('LATE_STEP_OUTPUTS'),
    late_screw_outputs: readWord('LATE_SCREW_OUTPUTS'),
    usb_configured: usbConfigured,
    usb_link_bytes_in: usbBytesIn,
    usb_link_bytes_out: usbBytesOut,
    usb_position_lines: usbLines,
    seed_program_starts: readWord('SEED_PROGRAM_STARTS'),
    bad_frames: readWord('BAD_FRAMES'),
    naks_sent: readWord('NAKS_SENT'),
    pc: mcu.core.PC,
  }));
  process.exit(0);
}
process.on('SIGTERM', finish);
process.on('SIGINT', finish);
run();
